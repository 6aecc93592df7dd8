"""The 4DGS Gaussian model (scene/gaussian_model.py): parameters, optimizer, densification.

Field names, optimizer group names, initialisation, learning-rate schedules, clone/split/prune,
opacity reset and ``capture()`` order are 4DGS's. Additions for plugins:

- ``deform(time, stage)`` returns a ``GaussianState`` (coarse: canonical; fine: through the
  deformation module, which a plugin may replace, with the registered per-Gaussian buffers).
- ``register_gaussian_buffer`` / ``register_gaussian_parameter``: per-Gaussian tensors that
  clone/split/prune keep in step (new rows copy their parent's values); parameters get their own
  optimizer group (named after them) handled like the built-in ones.
- ``freeze`` / ``unfreeze`` optimizer groups by name: frozen parameters get no gradient, hence
  no Adam update at all (not even from momentum).
- ``set_time_span((lo, hi), mode)``: what ``deform`` does at times outside [lo, hi] (the trainer
  sets the training views' span and ``--time_outside``): "extrapolate" (4DGS), "hold" (clamp the
  time) or "linear" (hold, with centres moved on at their velocity at the span's edge). Outside
  the span the field was never fitted; docs/TRAINING.md, "Times outside the training span".

Device: everything follows the point cloud given to ``create_from_pcd`` (or the restored
tensors); nothing is hard-coded.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable, Mapping, Sequence
from types import MappingProxyType
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor, nn

from baselines.fourdgs.deformation import DeformNetwork, check_deformation_state
from baselines.fourdgs.lr_schedule import get_expon_lr_func
from baselines.fourdgs.optimizer_state import check_state_by_group_name, load_state_by_group_name, swap_group_param
from baselines.fourdgs.state import STATE_FIELDS, GaussianState, activate_log_scales, stand_in

SH_C0 = 0.28209479177387814
TIME_OUTSIDE_MODES = ("extrapolate", "hold", "linear")  # see GaussianModel.set_time_span
# Per-Gaussian optimizer groups -> attribute, in 4DGS's group order around the module groups.
ROW_GROUPS: dict[str, str] = {
    "xyz": "_xyz",
    "f_dc": "_features_dc",
    "f_rest": "_features_rest",
    "opacity": "_opacity",
    "scaling": "_scaling",
    "rotation": "_rotation",
}
GROUP_ORDER: tuple[str, ...] = ("xyz", "deformation", "grid", "f_dc", "f_rest", "opacity", "scaling", "rotation")
STAGES: tuple[str, ...] = ("coarse", "fine")
# Names the deformation module receives beside the registered buffers (see deformation_inputs).
RESERVED_INPUTS: tuple[str, ...] = ("deformation_table", "row_gaussian")
CAPTURE_LENGTH_4DGS = 14


def inverse_sigmoid(x: Tensor) -> Tensor:
    return torch.log(x / (1 - x))


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC SH coefficient whose rendered colour (SH * C0 + 0.5) is ``rgb``."""
    return (rgb - 0.5) / SH_C0


def quaternion_to_matrix(rotations: Tensor) -> Tensor:
    """[N, 3, 3] rotation matrices of [N, 4] (w, x, y, z) quaternions (normalised first)."""
    w, x, y, z = F.normalize(rotations, dim=-1).unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        -1,
    ).reshape(-1, 3, 3)


def mean_squared_knn_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """[P] mean squared distance of each point to its ``k`` nearest others (simple-knn's distCUDA2)."""
    count = points.shape[0]
    if count < 2:
        raise ValueError(f"need at least 2 points to estimate initial scales, got {count}")
    neighbours = min(k, count - 1)
    distances, _ = cKDTree(points).query(points, k=neighbours + 1)
    return (distances[:, 1:] ** 2).mean(axis=1)


def _repeat_rows(tensor: Tensor, times: int) -> Tensor:
    """``tensor`` tiled ``times`` along dim 0 (4DGS's ``.repeat(N, 1, ...)``)."""
    return tensor.repeat(times, *([1] * (tensor.dim() - 1)))


def _opt_value(opt: Any, name: str) -> Any:
    try:
        return getattr(opt, name)
    except AttributeError:
        raise ValueError(f"optimization arguments lack {name!r} (4DGS OptimizationParams)") from None


def _without(used: Tensor | None, taken: Tensor | None, device: torch.device) -> Tensor | None:
    """[N] bool: the rows `used` (None: all) less those `taken` from another time (None: none)."""
    if taken is None:
        return used
    keep = ~taken.to(device)
    return keep if used is None else used.to(device) & keep


def _share_rows(states: list[GaussianState], shared: Sequence[tuple[int, Tensor] | None] | None) -> list[GaussianState]:
    """deform_many's last step: rows `mask` of states[k] replaced by states[j]'s for shared[k] = (j, mask)."""
    if shared is None:
        return states
    out = list(states)
    for k, entry in enumerate(shared):
        if entry is None:
            continue
        source, mask = states[entry[0]], entry[1]
        out[k] = GaussianState(*(
            getattr(states[k], name) if getattr(source, name) is getattr(states[k], name)
            else torch.where(mask.view(-1, *([1] * (getattr(source, name).dim() - 1))),
                             getattr(source, name), getattr(states[k], name))
            for name in STATE_FIELDS))
    return out


def _fused_adam_supported(device: torch.device) -> bool:
    """torch's fused Adam runs on CPU (torch >= 2.4) and CUDA; elsewhere the per-tensor one."""
    return torch.device(device).type in ("cpu", "cuda")


def _adam(groups: list[dict], fused: bool) -> torch.optim.Adam:
    """4DGS's Adam (eps 1e-15), fused where this torch build supports it for these parameters."""
    try:
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=fused or None)
    except RuntimeError:  # torch < 2.4 has no fused Adam on CPU: the per-tensor one
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)


class GaussianModel:
    """4DGS Gaussians plus their deformation module and optimizer.

    Args:
        sh_degree: maximum SH degree (4DGS default 3).
        hidden_args: 4DGS ModelHiddenParams-like object for the default deformation network.
        deformation: a module satisfying ``deformation.DeformationModule`` to use instead.
    """

    def __init__(self, sh_degree: int, hidden_args: Any = None, deformation: nn.Module | None = None) -> None:
        if sh_degree < 0:
            raise ValueError(f"sh_degree must be >= 0, got {sh_degree}")
        self.active_sh_degree = 0
        self.max_sh_degree = int(sh_degree)
        self._deformation = deformation if deformation is not None else DeformNetwork(hidden_args)
        rest = (self.max_sh_degree + 1) ** 2 - 1
        self._xyz = nn.Parameter(torch.empty(0, 3))
        self._features_dc = nn.Parameter(torch.empty(0, 1, 3))
        self._features_rest = nn.Parameter(torch.empty(0, rest, 3))
        self._scaling = nn.Parameter(torch.empty(0, 3))
        self._rotation = nn.Parameter(torch.empty(0, 4))
        self._opacity = nn.Parameter(torch.empty(0, 1))
        self._deformation_table = torch.empty(0, dtype=torch.bool)
        self.time_span: tuple[float, float] | None = None  # see set_time_span
        self.time_outside = "extrapolate"
        self._deformation_accum = torch.empty(0, 3)
        self.max_radii2D = torch.empty(0)
        self.xyz_gradient_accum = torch.empty(0, 1)
        self.denom = torch.empty(0, 1)
        self.optimizer: torch.optim.Optimizer | None = None
        self.percent_dense = 0.0
        self.spatial_lr_scale = 0.0
        self.xyz_scheduler_args = self.deformation_scheduler_args = self.grid_scheduler_args = None
        self._extra_buffers: dict[str, Tensor] = {}
        self._extra_params: dict[str, nn.Parameter] = {}
        self._extra_param_lrs: dict[str, float] = {}
        # group name -> {id(param): requires_grad before freezing}
        self._frozen: dict[str, dict[int, bool]] = {}
        # group name -> multiplier of its learning rate (plugins; applied on top of the schedules)
        self._lr_scales: dict[str, float] = {}

    # ========================================================================================
    # Activated views (4DGS property names) and basic facts.
    @property
    def get_xyz(self) -> Tensor:
        return self._xyz

    @property
    def get_scaling(self) -> Tensor:
        return activate_log_scales(self._scaling)

    @property
    def get_rotation(self) -> Tensor:
        return F.normalize(self._rotation, dim=-1)

    @property
    def get_opacity(self) -> Tensor:
        return torch.sigmoid(self._opacity)

    @property
    def get_features(self) -> Tensor:
        return torch.cat((self._features_dc, self._features_rest), 1)

    @property
    def get_aabb(self) -> tuple[Tensor, Tensor]:
        return self._deformation.get_aabb

    @property
    def num_gaussians(self) -> int:
        return self._xyz.shape[0]

    @property
    def device(self) -> torch.device:
        return self._xyz.device

    @property
    def deformation(self) -> nn.Module:
        return self._deformation

    def oneupSHdegree(self) -> None:
        if self.active_sh_degree < self.max_sh_degree:
            self.active_sh_degree += 1

    # ========================================================================================
    # Initialisation.
    def create_from_pcd(
        self, points: Any, colors: Any, spatial_lr_scale: float, device: torch.device | str | None = None
    ) -> None:
        """4DGS initialisation from a coloured point cloud.

        Args:
            points: [P, 3] positions (numpy or tensor; a tensor's device is used unless
                ``device`` is given).
            colors: [P, 3] RGB in [0, 1].
            spatial_lr_scale: scene extent scaling the position/deformation/grid learning rates.
        """
        if device is None:
            device = points.device if isinstance(points, Tensor) else torch.device("cpu")
        xyz = torch.as_tensor(np.asarray(points.detach().cpu() if isinstance(points, Tensor) else points),
                              dtype=torch.float32)
        rgb = torch.as_tensor(np.asarray(colors.detach().cpu() if isinstance(colors, Tensor) else colors),
                              dtype=torch.float32)
        if xyz.dim() != 2 or xyz.shape[1] != 3:
            raise ValueError(f"create_from_pcd: points must be [P, 3], got {list(xyz.shape)}")
        if rgb.shape != xyz.shape:
            raise ValueError(f"create_from_pcd: colors must be [P, 3] = {list(xyz.shape)}, got {list(rgb.shape)}")
        if not torch.isfinite(xyz).all() or not torch.isfinite(rgb).all():
            raise ValueError("create_from_pcd: points or colors contain NaN or inf")
        count = xyz.shape[0]
        dist2 = torch.from_numpy(mean_squared_knn_distance(xyz.numpy().astype(np.float64))).float()
        log_scales = torch.log(torch.sqrt(dist2.clamp_min(1e-7)))[:, None].repeat(1, 3)
        rotations = torch.zeros(count, 4)
        rotations[:, 0] = 1.0
        features = torch.zeros(count, (self.max_sh_degree + 1) ** 2, 3)
        features[:, 0] = rgb_to_sh(rgb)

        self.spatial_lr_scale = float(spatial_lr_scale)
        self._deformation = self._deformation.to(device)
        if hasattr(self._deformation, "set_aabb"):
            self._deformation.set_aabb(xyz.max(0).values, xyz.min(0).values)
        rows = {
            "xyz": xyz,
            "f_dc": features[:, :1].contiguous(),
            "f_rest": features[:, 1:].contiguous(),
            "opacity": inverse_sigmoid(torch.full((count, 1), 0.1)),
            "scaling": log_scales,
            "rotation": rotations,
        }
        self.set_gaussians(rows, device=device)
        self.set_extras({}, {}, {}, "create_from_pcd")

    def set_gaussians(
        self,
        rows: Mapping[str, Tensor],
        deformation_table: Tensor | None = None,
        deformation_accum: Tensor | None = None,
        device: torch.device | str | None = None,
        source: str = "set_gaussians",
    ) -> None:
        """Install Gaussians: ``rows`` has the keys of ``ROW_GROUPS`` (pre-activation values).

        The deformation table defaults to all True and the accumulator to zeros; statistics
        restart at zero and the optimizer is dropped (call ``training_setup`` again).
        Registered buffers/parameters are left alone (see ``set_extras``).
        """
        self.check_rows(rows, source)
        count = rows["xyz"].shape[0]
        device = torch.device(device) if device is not None else rows["xyz"].device
        if deformation_table is None:
            deformation_table = torch.ones(count, dtype=torch.bool)
        if deformation_accum is None:
            deformation_accum = torch.zeros(count, 3)
        if deformation_table.shape != (count,) or deformation_accum.shape != (count, 3):
            raise ValueError(
                f"{source}: deformation table {list(deformation_table.shape)} / accumulator "
                f"{list(deformation_accum.shape)} do not fit {count} Gaussians"
            )
        self._set_rows(**{name: value.to(device, torch.float32) for name, value in rows.items()})
        self._deformation_table = deformation_table.to(device, torch.bool)
        self._deformation_accum = deformation_accum.to(device, torch.float32)
        self._reset_stats(count, device)
        self.optimizer = None

    def _set_rows(self, **rows: Tensor) -> None:
        """Install fresh per-Gaussian parameters (no optimizer bookkeeping)."""
        for name, value in rows.items():
            param = nn.Parameter(value.detach(), requires_grad=name not in self._frozen)
            setattr(self, ROW_GROUPS[name], param)

    def _reset_stats(self, count: int, device: torch.device) -> None:
        self.xyz_gradient_accum = torch.zeros(count, 1, device=device)
        self.denom = torch.zeros(count, 1, device=device)
        self.max_radii2D = torch.zeros(count, device=device)

    # ========================================================================================
    # Optimizer.
    def training_setup(self, opt: Any) -> None:
        """Adam (eps 1e-15) with 4DGS's named groups plus one group per registered parameter."""
        if self.spatial_lr_scale <= 0:
            raise ValueError(
                "training_setup: spatial_lr_scale is 0; call create_from_pcd or set spatial_lr_scale "
                "(the cameras' extent) first"
            )
        scale = self.spatial_lr_scale
        self.percent_dense = float(_opt_value(opt, "percent_dense"))
        count, device = self.num_gaussians, self.device
        self.xyz_gradient_accum = torch.zeros(count, 1, device=device)
        self.denom = torch.zeros(count, 1, device=device)
        self._deformation_accum = torch.zeros(count, 3, device=device)
        feature_lr = float(_opt_value(opt, "feature_lr"))
        lrs = {
            "xyz": _opt_value(opt, "position_lr_init") * scale,
            "deformation": _opt_value(opt, "deformation_lr_init") * scale,
            "grid": _opt_value(opt, "grid_lr_init") * scale,
            "f_dc": feature_lr,
            "f_rest": feature_lr / 20.0,
            "opacity": _opt_value(opt, "opacity_lr"),
            "scaling": _opt_value(opt, "scaling_lr"),
            "rotation": _opt_value(opt, "rotation_lr"),
        }
        for name, (schedule, _) in self._module_groups().items():
            lrs[name] = lrs[schedule]  # a deformation module's own group starts on its schedule's rate
        groups = [{"params": self._group_params(name), "lr": float(lrs[name]) * self._lr_scales.get(name, 1.0),
                   "name": name} for name in (*GROUP_ORDER, *self._module_groups())]
        groups += [{"params": [p], "lr": self._extra_param_lrs[n] * self._lr_scales.get(n, 1.0), "name": n}
                   for n, p in self._extra_params.items()]
        # fused: one kernel per group instead of ~10 ops per tensor (the deformation group alone
        # holds 20+ tensors); same update up to float rounding
        self.optimizer = _adam(groups, fused=_fused_adam_supported(device))

        max_steps = _opt_value(opt, "position_lr_max_steps")
        deformation_delay = _opt_value(opt, "deformation_lr_delay_mult")
        self.xyz_scheduler_args = get_expon_lr_func(
            lr_init=_opt_value(opt, "position_lr_init") * scale,
            lr_final=_opt_value(opt, "position_lr_final") * scale,
            lr_delay_mult=_opt_value(opt, "position_lr_delay_mult"),
            max_steps=max_steps,
        )
        self.deformation_scheduler_args = get_expon_lr_func(
            lr_init=_opt_value(opt, "deformation_lr_init") * scale,
            lr_final=_opt_value(opt, "deformation_lr_final") * scale,
            lr_delay_mult=deformation_delay,
            max_steps=max_steps,
        )
        self.grid_scheduler_args = get_expon_lr_func(
            lr_init=_opt_value(opt, "grid_lr_init") * scale,
            lr_final=_opt_value(opt, "grid_lr_final") * scale,
            lr_delay_mult=deformation_delay,
            max_steps=max_steps,
        )

    def update_learning_rate(self, iteration: int) -> dict[str, float]:
        """Apply the xyz/deformation/grid schedules at ``iteration``; returns the rates set."""
        if self.optimizer is None:
            raise ValueError("update_learning_rate: call training_setup first")
        schedules = {
            "xyz": self.xyz_scheduler_args,
            "deformation": self.deformation_scheduler_args,
            "grid": self.grid_scheduler_args,
        }
        for name, (schedule, _) in self._module_groups().items():
            schedules[name] = schedules[schedule]
        rates = {}
        for group in self.optimizer.param_groups:
            schedule = schedules.get(group["name"])
            if schedule is not None:
                group["lr"] = rates[group["name"]] = schedule(iteration) * self._lr_scales.get(group["name"], 1.0)
        return rates

    def scale_learning_rate(self, group_name: str, factor: float) -> None:
        """Multiply a group's learning rate (and its schedule) by ``factor`` from now on.

        Persistent across ``training_setup`` (every stage); ``factor`` 1 restores the default.
        E.g. a deformation module that moves only a few Gaussians may learn faster than 4DGS's.
        """
        if group_name not in self.group_names:
            raise ValueError(f"unknown parameter group {group_name!r} (groups: {self.group_names})")
        if not factor > 0:
            raise ValueError(f"scale_learning_rate: factor must be > 0, got {factor}")
        previous = self._lr_scales.get(group_name, 1.0)
        self._lr_scales[group_name] = float(factor)
        if self.optimizer is not None:
            for group in self.optimizer.param_groups:
                if group["name"] == group_name:
                    group["lr"] *= factor / previous

    @property
    def learning_rate_scales(self) -> Mapping[str, float]:
        return MappingProxyType(self._lr_scales)

    @property
    def group_names(self) -> list[str]:
        """Every optimizer group name: 4DGS's eight, the deformation module's own, then registered parameters."""
        return list(GROUP_ORDER) + list(self._module_groups()) + list(self._extra_params)

    def _module_groups(self) -> Mapping[str, tuple[str, list[nn.Parameter]]]:
        """The deformation module's groups beyond 4DGS's two (optional ``scheduled_groups()``):
        name -> (the host schedule it follows, "deformation" or "grid"; its parameters)."""
        extra = getattr(self._deformation, "scheduled_groups", None)
        groups = dict(extra()) if extra is not None else {}
        for name, (schedule, _) in groups.items():
            if name in GROUP_ORDER or schedule not in ("deformation", "grid"):
                raise ValueError(f"deformation module group {name!r}: the name must be new and the schedule "
                                 f"'deformation' or 'grid', got {schedule!r}")
        return groups

    def _group_params(self, name: str) -> list[nn.Parameter]:
        if name in ROW_GROUPS:
            return [getattr(self, ROW_GROUPS[name])]
        if name == "deformation":
            return list(self._deformation.get_mlp_parameters())
        if name == "grid":
            return list(self._deformation.get_grid_parameters())
        if name in self._extra_params:
            return [self._extra_params[name]]
        module_groups = self._module_groups()
        if name in module_groups:
            return list(module_groups[name][1])
        raise ValueError(f"unknown parameter group {name!r} (groups: {self.group_names})")

    # ----------------------------------------------------------------------------------------
    def freeze(self, group_names: str | Iterable[str]) -> None:
        """Stop updating the named groups (e.g. "deformation", "grid"): no gradient, no Adam step."""
        names = [group_names] if isinstance(group_names, str) else list(group_names)
        for name in names:
            params = self._group_params(name)
            if name in self._frozen:
                continue
            self._frozen[name] = {id(p): p.requires_grad for p in params}
            for p in params:
                p.requires_grad_(False)
                p.grad = None

    def unfreeze(self, group_names: str | Iterable[str]) -> None:
        """Undo ``freeze`` (parameters get back the trainability they had)."""
        names = [group_names] if isinstance(group_names, str) else list(group_names)
        for name in names:
            params = self._group_params(name)
            saved = self._frozen.pop(name, None)
            if saved is None:
                continue
            for p in params:
                p.requires_grad_(saved.get(id(p), True))

    @property
    def frozen_groups(self) -> list[str]:
        return list(self._frozen)

    # ========================================================================================
    # Per-Gaussian buffers and parameters registered by plugins.
    def _check_new_name(self, name: str, tensor: Tensor) -> None:
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"per-Gaussian attribute name must be an identifier, got {name!r}")
        if name in GROUP_ORDER or name in RESERVED_INPUTS or name in self._extra_buffers or name in self._extra_params:
            raise ValueError(f"per-Gaussian attribute {name!r} already exists")
        if not isinstance(tensor, Tensor) or tensor.dim() == 0 or tensor.shape[0] != self.num_gaussians:
            shape = list(tensor.shape) if isinstance(tensor, Tensor) else type(tensor).__name__
            raise ValueError(
                f"per-Gaussian attribute {name!r}: first dimension must be {self.num_gaussians}, got {shape}"
            )

    def register_gaussian_buffer(self, name: str, tensor: Tensor) -> None:
        """A non-trainable per-Gaussian tensor [N, ...] kept in step by clone/split/prune."""
        self._check_new_name(name, tensor)
        self._extra_buffers[name] = tensor.detach().to(self.device)

    def set_gaussian_buffer(self, name: str, tensor: Tensor) -> None:
        """Replace a registered buffer's values (same shape)."""
        if name not in self._extra_buffers:
            raise ValueError(f"no registered per-Gaussian buffer {name!r} (have {list(self._extra_buffers)})")
        old = self._extra_buffers[name]
        if tensor.shape != old.shape:
            raise ValueError(f"buffer {name!r}: expected shape {list(old.shape)}, got {list(tensor.shape)}")
        self._extra_buffers[name] = tensor.detach().to(old.device, old.dtype)

    def pop_gaussian_buffer(self, name: str) -> Tensor:
        """Unregister a buffer and return its (current, densification-updated) values."""
        if name not in self._extra_buffers:
            raise ValueError(f"no registered per-Gaussian buffer {name!r} (have {list(self._extra_buffers)})")
        return self._extra_buffers.pop(name)

    def register_gaussian_parameter(self, name: str, tensor: Tensor, lr: float) -> nn.Parameter:
        """A trainable per-Gaussian tensor [N, ...] with its own Adam group ``name`` at rate ``lr``."""
        self._check_new_name(name, tensor)
        if not tensor.is_floating_point():
            raise ValueError(f"per-Gaussian parameter {name!r} must be floating point, got {tensor.dtype}")
        param = nn.Parameter(tensor.detach().to(self.device).clone())
        self._extra_params[name] = param
        self._extra_param_lrs[name] = float(lr)
        if self.optimizer is not None:
            self.optimizer.add_param_group({"params": [param], "lr": float(lr), "name": name})
        return param

    @property
    def registered_buffers(self) -> Mapping[str, Tensor]:
        return MappingProxyType(self._extra_buffers)

    @property
    def registered_parameters(self) -> Mapping[str, nn.Parameter]:
        return MappingProxyType(self._extra_params)

    @property
    def registered_parameter_lrs(self) -> Mapping[str, float]:
        return MappingProxyType(self._extra_param_lrs)

    @property
    def gaussian_buffers(self) -> Mapping[str, Tensor]:
        """Registered per-Gaussian buffers and parameters by name (read-only mapping)."""
        return MappingProxyType({**self._extra_buffers, **self._extra_params})

    # ========================================================================================
    # States handed to the renderer.
    def canonical_state(self) -> GaussianState:
        """The stored (canonical, pre-activation) Gaussians."""
        return GaussianState(self._xyz, self._scaling, self._rotation, self._opacity, self.get_features)

    def set_time_span(self, span: tuple[float, float] | None, mode: str = "linear") -> None:
        """The times the deformation was fitted on, and what ``deform`` does outside them.

        Args:
            span: (lo, hi) or None (no span: every time is evaluated as it is).
            mode: "extrapolate" (evaluate the field at the time as given), "hold" (at the time
                clamped into the span) or "linear" (as "hold", then each centre moves on by its
                finite-difference velocity at the edge: x(t) = 2 x(t_c) - x(2 t_c - t), with the
                mirrored time clamped into the span; scales, rotations, opacities, colours held).
        """
        if mode not in TIME_OUTSIDE_MODES:
            raise ValueError(f"set_time_span: mode must be one of {TIME_OUTSIDE_MODES}, got {mode!r}")
        if span is not None:
            lo, hi = float(span[0]), float(span[1])
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"set_time_span: need finite lo <= hi, got {span}")
            span = (lo, hi)
        self.time_span, self.time_outside = span, mode

    def _times(self, time: float | Tensor) -> Tensor:
        """[N, 1] per-Gaussian times from a scalar, [N] or [N, 1] time."""
        count = self.num_gaussians
        if not isinstance(time, Tensor):
            return torch.full((count, 1), float(time), device=self.device, dtype=self._xyz.dtype)
        time = time.to(self.device, self._xyz.dtype)
        if time.numel() == 1:
            return time.reshape(1, 1).expand(count, 1)
        if time.shape in ((count,), (count, 1)):
            return time.reshape(count, 1)
        raise ValueError(f"deform: time must be a scalar, [N] or [N, 1] with N={count}, got {list(time.shape)}")

    def deformation_inputs(self) -> Mapping[str, Tensor]:
        """What the deformation module receives besides the state and times: the registered
        per-Gaussian buffers and parameters, plus ``deformation_table`` ([N] bool, 4DGS's
        "this Gaussian is deformed" flag; a module may skip the rows that are False).
        ``deform_many`` adds ``row_gaussian`` ([kN] long: the Gaussian each of its repeated rows
        is), so a module may compute a time-independent term once per Gaussian."""
        return MappingProxyType({**self._extra_buffers, **self._extra_params,
                                 "deformation_table": self._deformation_table})

    def deform(self, time: float | Tensor, stage: str) -> GaussianState:
        """Gaussians at ``time`` (scalar or per-Gaussian): canonical in the coarse stage."""
        if stage not in STAGES:
            raise ValueError(f"deform: stage must be one of {STAGES}, got {stage!r}")
        state = self.canonical_state()
        if stage == "coarse":
            return state
        times, inputs = self._times(time), self.deformation_inputs()
        span = self.time_span
        inside = span is not None and not isinstance(time, Tensor) and span[0] <= time <= span[1]
        if span is None or self.time_outside == "extrapolate" or inside:  # inside: no tensor check (hot path)
            return self._deformation(state, times, inputs)
        held = times.clamp(self.time_span[0], self.time_span[1])
        out = self._deformation(state, held, inputs)
        if self.time_outside == "linear" and bool((held != times).any()):
            # centres continue at the edge velocity; the mirrored time stays inside the span
            mirrored = (2.0 * held - times).clamp(self.time_span[0], self.time_span[1])
            before = self._deformation(state, mirrored, inputs).means
            out = out.replace(means=2.0 * out.means - before)
        return out

    def deform_many(self, times: Sequence[float], stage: str,
                    rows: Sequence[Tensor | None] | None = None,
                    shared: Sequence[tuple[int, Tensor] | None] | None = None) -> list[GaussianState]:
        """The Gaussians at each of `times` (scalars), equal to ``[deform(t, stage) for t in times]``.

        Several times inside the training span go through the deformation module in ONE call on
        the state repeated once per time (rows [k N, (k + 1) N) at times[k]): the per-call work of
        a HexPlane field and its MLP (hundreds of small kernels on a GPU) is paid once for a
        view and its partner frame. A time outside the span (its clamping and extrapolation) or a
        single time takes ``deform``'s path.

        `rows[k]` ([N] bool, or None for all): the Gaussians whose state at times[k] the caller
        reads. The module gets them as ``buffers["row_used"]`` ([kN] bool) and may leave the other
        rows undeformed (equal to the canonical state); on ``deform``'s path every row is deformed.

        `shared[k]` = (j, mask [N] bool), or None: the Gaussians in `mask` take at times[k] their
        state at times[j] (values, and gradients through times[j]'s deformation), so the module
        need not deform them at times[k] (they leave ``row_used``). E.g. ReFlow's static field read
        at the batch view's time for the view's partner frame: the flow of a static Gaussian is
        then the camera's alone.
        """
        if rows is not None and len(rows) != len(times):
            raise ValueError(f"deform_many: {len(rows)} row masks for {len(times)} times")
        shared = self._check_shared(shared, len(times))
        if shared is not None:  # rows taken from another time are not deformed at this one
            rows = [_without(None if rows is None else rows[k], None if s is None else s[1], self.device)
                    for k, s in enumerate(shared)]
        times = [float(t) for t in times]
        span = self.time_span
        outside = span is not None and self.time_outside != "extrapolate" and not all(
            span[0] <= t <= span[1] for t in times)
        if stage != "fine" or len(times) < 2 or outside:
            return _share_rows([self.deform(t, stage) for t in times], shared)
        state, count = self.canonical_state(), self.num_gaussians
        # fields the module passes through unread are not repeated (SH: 48 of a row's 59 values)
        passed = getattr(self._deformation, "passed_through", frozenset)()
        repeated = GaussianState(*(stand_in(getattr(state, name), len(times) * count) if name in passed
                                   else torch.cat([getattr(state, name)] * len(times)) for name in STATE_FIELDS))
        column = torch.tensor(times, device=self.device, dtype=self._xyz.dtype).repeat_interleave(count).unsqueeze(1)
        # per-Gaussian inputs (registered buffers, deformation_table) follow the repeated rows
        inputs = {name: torch.cat([value] * len(times)) for name, value in self.deformation_inputs().items()}
        # which Gaussian each repeated row is: a module may compute a time-independent term once per Gaussian
        inputs["row_gaussian"] = torch.arange(count, device=self.device).repeat(len(times))
        if rows is not None and any(r is not None for r in rows):
            for r in rows:
                if r is not None and (r.dtype != torch.bool or tuple(r.shape) != (count,)):
                    raise ValueError(f"deform_many: a row mask must be [{count}] bool, got {r.dtype} {list(r.shape)}")
            inputs["row_used"] = torch.cat([torch.ones(count, dtype=torch.bool, device=self.device) if r is None
                                            else r.to(self.device) for r in rows])
        out = self._deformation(repeated, column, inputs)
        for name in passed:
            if getattr(out, name) is not getattr(repeated, name):
                raise RuntimeError(f"deform_many: {type(self._deformation).__name__} changed {name}, which its "
                                   "passed_through() says it returns untouched")
        # A field the module passed through unchanged (4DGS's disabled heads: SH, opacity) is the
        # canonical tensor at every time: its gradient then reaches the parameter directly instead
        # of through k slices and a concatenation of [kN, ...] zeros (same values and gradients).
        kept = {name: getattr(state, name) for name in STATE_FIELDS if getattr(out, name) is getattr(repeated, name)}
        return _share_rows([out.index(slice(k * count, (k + 1) * count)).replace(**kept)
                            for k in range(len(times))], shared)

    def _check_shared(self, shared: Sequence[tuple[int, Tensor] | None] | None,
                      count: int) -> list[tuple[int, Tensor] | None] | None:
        """deform_many's `shared`, checked: one entry per time, each (another time's index, [N] bool)."""
        if shared is None or all(s is None for s in shared):
            return None
        if len(shared) != count:
            raise ValueError(f"deform_many: {len(shared)} shared-row entries for {count} times")
        checked: list[tuple[int, Tensor] | None] = []
        for k, entry in enumerate(shared):
            if entry is None:
                checked.append(None)
                continue
            source, mask = entry
            if not 0 <= int(source) < count or int(source) == k or shared[int(source)] is not None:
                raise ValueError(f"deform_many: time {k} takes its shared rows from time {source}, which must be "
                                 f"another of the {count} times and share none itself")
            if mask.dtype != torch.bool or tuple(mask.shape) != (self.num_gaussians,):
                raise ValueError(f"deform_many: a shared-row mask must be [{self.num_gaussians}] bool, "
                                 f"got {mask.dtype} {list(mask.shape)}")
            checked.append((int(source), mask.to(self.device)))
        return checked

    @property
    def deformation_table(self) -> Tensor:
        """[N] bool, True where the Gaussian is deformed (4DGS's ``_deformation_table``)."""
        return self._deformation_table

    def set_deformation_table(self, table: Tensor) -> None:
        """Replace the [N] bool deformation table (kept in step by clone/split/prune, saved as
        ``deformation_table.pth``)."""
        if table.shape != (self.num_gaussians,):
            raise ValueError(f"set_deformation_table: expected [{self.num_gaussians}], got {list(table.shape)}")
        self._deformation_table = table.detach().to(self.device, torch.bool).clone()

    def compute_regulation(
        self, time_smoothness_weight: float, l1_time_planes_weight: float, plane_tv_weight: float
    ) -> Tensor:
        """4DGS's HexPlane regularisers (delegated to the deformation module)."""
        return self._deformation.compute_regulation(time_smoothness_weight, l1_time_planes_weight, plane_tv_weight)

    # ========================================================================================
    # Row edits shared by prune / densify / reset, keeping Adam state and buffers in step.
    def _row_param_names(self) -> list[str]:
        return list(ROW_GROUPS) + list(self._extra_params)

    def _get_row_param(self, name: str) -> nn.Parameter:
        return getattr(self, ROW_GROUPS[name]) if name in ROW_GROUPS else self._extra_params[name]

    def _install_row_param(self, name: str, data: Tensor, map_rows) -> None:
        param = nn.Parameter(data, requires_grad=name not in self._frozen)
        if self.optimizer is not None:
            swap_group_param(self.optimizer, name, param, map_rows)
        if name in ROW_GROUPS:
            setattr(self, ROW_GROUPS[name], param)
        else:
            self._extra_params[name] = param

    def _keep_rows(self, keep: Tensor) -> None:
        for name in self._row_param_names():
            self._install_row_param(name, self._get_row_param(name).detach()[keep], lambda t: t[keep])
        self._deformation_accum = self._deformation_accum[keep]
        self.xyz_gradient_accum = self.xyz_gradient_accum[keep]
        self._deformation_table = self._deformation_table[keep]
        self.denom = self.denom[keep]
        self.max_radii2D = self.max_radii2D[keep]
        for name, value in self._extra_buffers.items():
            self._extra_buffers[name] = value[keep]

    @torch.no_grad()
    def prune_points(self, mask: Tensor) -> None:
        """Remove the Gaussians where ``mask`` [N] (bool) is True."""
        if mask.dtype != torch.bool or mask.shape != (self.num_gaussians,):
            raise ValueError(
                f"prune_points: mask must be bool [{self.num_gaussians}], got {mask.dtype} {list(mask.shape)}"
            )
        self._keep_rows(~mask)

    @torch.no_grad()
    def permute_rows(self, order: Tensor) -> None:
        """Reorder the Gaussians: row i becomes old row ``order[i]`` ([N] int64, a permutation) in
        every per-Gaussian parameter, its Adam moments, the statistics and the buffers (row_order.py).
        The parameters are replaced, so gradients already computed are dropped (as densification does)."""
        count = self.num_gaussians
        if order.dtype != torch.int64 or order.shape != (count,):
            raise ValueError(f"permute_rows: order must be int64 [{count}], got {order.dtype} {list(order.shape)}")
        order = order.to(self.device)
        in_range = bool(((order >= 0) & (order < count)).all())
        if not (in_range and bool((torch.bincount(order, minlength=count) == 1).all())):
            raise ValueError(f"permute_rows: order is not a permutation of 0..{count - 1}")
        self._keep_rows(order)

    def _rows_of(self, selection: Tensor, repeats: int = 1) -> dict[str, Tensor]:
        """Every per-Gaussian parameter and buffer at ``selection``, tiled ``repeats`` times."""
        rows = {name: _repeat_rows(self._get_row_param(name).detach()[selection], repeats)
                for name in self._row_param_names()}
        rows["deformation_table"] = _repeat_rows(self._deformation_table[selection], repeats)
        for name, value in self._extra_buffers.items():
            rows[name] = _repeat_rows(value[selection], repeats)
        return rows

    def densification_postfix(self, new_rows: Mapping[str, Tensor]) -> None:
        """Append Gaussians (every per-Gaussian parameter and buffer given by name) and, as 4DGS
        does, reset the gradient statistics, max radii and deformation accumulators of all."""
        for name in self._row_param_names():
            new = new_rows[name]
            data = torch.cat((self._get_row_param(name).detach(), new), 0)
            self._install_row_param(name, data, lambda t, new=new: torch.cat((t, torch.zeros_like(new)), 0))
        self._deformation_table = torch.cat((self._deformation_table, new_rows["deformation_table"]), 0)
        for name, value in self._extra_buffers.items():
            self._extra_buffers[name] = torch.cat((value, new_rows[name].to(value.dtype)), 0)
        count, device = self.num_gaussians, self.device
        self._reset_stats(count, device)
        self._deformation_accum = torch.zeros(count, 3, device=device)

    @torch.no_grad()
    def densify_and_clone(self, grads: Tensor, grad_threshold: float, scene_extent: float) -> int:
        """Copy small Gaussians with large view-space gradients; returns how many were added."""
        selected = torch.norm(grads, dim=-1) >= grad_threshold
        selected &= self.get_scaling.max(dim=1).values <= self.percent_dense * scene_extent
        self.densification_postfix(self._rows_of(selected))
        return int(selected.sum())

    @torch.no_grad()
    def densify_and_split(self, grads: Tensor, grad_threshold: float, scene_extent: float, N: int = 2) -> int:
        """Replace large Gaussians with large gradients by ``N`` smaller samples; returns how many split."""
        count = self.num_gaussians
        padded = torch.zeros(count, device=self.device)
        padded[: grads.shape[0]] = grads.squeeze(-1)
        selected = padded >= grad_threshold
        selected &= self.get_scaling.max(dim=1).values > self.percent_dense * scene_extent
        num_selected = int(selected.sum())
        if num_selected == 0:
            return 0
        stds = _repeat_rows(self.get_scaling.detach()[selected], N)
        samples = torch.normal(mean=torch.zeros_like(stds), std=stds)
        rotations = _repeat_rows(quaternion_to_matrix(self._rotation.detach()[selected]), N)
        rows = self._rows_of(selected, N)
        rows["xyz"] = torch.bmm(rotations, samples.unsqueeze(-1)).squeeze(-1) + rows["xyz"]
        rows["scaling"] = torch.log(stds / (0.8 * N))
        self.densification_postfix(rows)
        prune = torch.cat((selected, torch.zeros(N * num_selected, device=self.device, dtype=torch.bool)))
        self.prune_points(prune)
        return num_selected

    @torch.no_grad()
    def densify(self, max_grad: float, extent: float) -> tuple[int, int]:
        """4DGS's ``densify``: clone then split by mean view-space gradient; returns (cloned, split)."""
        grads = self.xyz_gradient_accum / self.denom
        grads[grads.isnan()] = 0.0
        cloned = self.densify_and_clone(grads, max_grad, extent)
        split = self.densify_and_split(grads, max_grad, extent)
        return cloned, split

    @torch.no_grad()
    def prune(self, min_opacity: float, extent: float, max_screen_size: float | None,
              protect: Tensor | None = None) -> int:
        """4DGS's ``prune``: transparent Gaussians, and (with ``max_screen_size``) too large ones.

        ``protect`` [N] bool (ours): Gaussians kept whatever the criteria say.
        """
        mask = (self.get_opacity < min_opacity).squeeze(-1)
        if max_screen_size:
            mask |= self.max_radii2D > max_screen_size
            mask |= self.get_scaling.max(dim=1).values > 0.1 * extent
        if protect is not None:
            mask &= ~protect.to(mask.device, torch.bool)
        self.prune_points(mask)
        return int(mask.sum())

    @torch.no_grad()
    def reset_opacity(self) -> None:
        """Clamp opacities to at most 0.01 and restart their Adam moments."""
        opacities = inverse_sigmoid(torch.clamp(self.get_opacity.detach(), max=0.01))
        self._install_row_param("opacity", opacities, None)

    @torch.no_grad()
    def zero_row_gradients(self, rows: Tensor) -> None:
        """Zero every per-Gaussian gradient of the rows where ``rows`` [N] bool is True.

        Per-row freezing for one step: call after backward, before the optimizer step (Adam
        still applies the rows' existing momentum, so rows frozen from the start never move).
        """
        if rows.shape != (self.num_gaussians,):
            raise ValueError(f"zero_row_gradients: rows must be [{self.num_gaussians}] bool, got {list(rows.shape)}")
        rows = rows.to(self.device, torch.bool)
        for name in self._row_param_names():
            grad = self._get_row_param(name).grad
            if grad is not None:
                grad[rows] = 0

    # ----------------------------------------------------------------------------------------
    @torch.no_grad()
    def add_densification_stats(self, means2d_grad: Tensor, visible: Tensor, width: int, height: int) -> None:
        """Accumulate view-space gradient norms of visible Gaussians.

        ``means2d_grad`` [N, 2] is in pixel units (summed over the batch's views); it is converted
        to the NDC units of 3DGS/4DGS's rasterizer (x * W/2, y * H/2) so that 4DGS's thresholds
        (e.g. 0.0002) keep their meaning.
        """
        count = self.num_gaussians
        if means2d_grad.shape != (count, 2):
            raise ValueError(
                f"add_densification_stats: means2d_grad must be [{count}, 2], got {list(means2d_grad.shape)}"
            )
        if visible.shape != (count,) or visible.dtype != torch.bool:
            raise ValueError(
                f"add_densification_stats: visible must be bool [{count}], got {visible.dtype} {list(visible.shape)}"
            )
        to_ndc = means2d_grad.new_tensor([0.5 * width, 0.5 * height])
        norms = torch.norm(means2d_grad.detach() * to_ndc, dim=-1, keepdim=True)
        self.xyz_gradient_accum[visible] += norms[visible]
        self.denom[visible] += 1

    @torch.no_grad()
    def update_max_radii(self, radii: Tensor, visible: Tensor) -> None:
        """max_radii2D = max(max_radii2D, radii) on visible Gaussians (radii [N] in pixels)."""
        radii = radii.detach().to(self.max_radii2D.dtype)
        self.max_radii2D[visible] = torch.max(self.max_radii2D[visible], radii[visible])

    # ========================================================================================
    # Whole-model snapshots (4DGS's checkpoint tuple).
    def capture(self) -> tuple:
        """4DGS's 14-tuple (copies, so later training does not alter it) plus our extras dict."""
        if self.optimizer is None:
            raise ValueError("capture: call training_setup first (the snapshot includes the optimizer)")

        def snap(t: Tensor) -> Tensor:
            return t.detach().clone()

        extras = {
            "deformation_accum": snap(self._deformation_accum),
            "buffers": {n: snap(v) for n, v in self._extra_buffers.items()},
            "parameters": {n: snap(v) for n, v in self._extra_params.items()},
            "parameter_lrs": dict(self._extra_param_lrs),
            "frozen": list(self._frozen),
        }
        return (
            self.active_sh_degree,
            snap(self._xyz),
            {k: snap(v) for k, v in self._deformation.state_dict().items()},
            snap(self._deformation_table),
            snap(self._features_dc),
            snap(self._features_rest),
            snap(self._scaling),
            snap(self._rotation),
            snap(self._opacity),
            snap(self.max_radii2D),
            snap(self.xyz_gradient_accum),
            snap(self.denom),
            copy.deepcopy(self.optimizer.state_dict()),
            self.spatial_lr_scale,
            extras,
        )

    def restore(self, captured: tuple | list, opt: Any, source: str = "checkpoint",
                device: torch.device | str | None = None) -> None:
        """Load a ``capture()`` (ours, or 4DGS's 14-tuple) and rebuild the optimizer with ``opt``.

        The model goes to `device` (default: where the captured positions are; a checkpoint is
        loaded on the CPU, so a CUDA run passes its device).

        Registered buffers/parameters and frozen groups become those of the snapshot (none for
        4DGS's). Everything is checked before the model is changed.
        """
        lengths = (CAPTURE_LENGTH_4DGS, CAPTURE_LENGTH_4DGS + 1)
        if not isinstance(captured, (tuple, list)) or len(captured) not in lengths:
            raise ValueError(f"{source}: expected 4DGS's 14-element capture tuple (optionally + extras)")
        (active_sh_degree, xyz, deformation_state, table, f_dc, f_rest, scaling, rotation, opacity,
         max_radii, grad_accum, denom, optimizer_state, spatial_lr_scale) = captured[:CAPTURE_LENGTH_4DGS]
        extras = captured[CAPTURE_LENGTH_4DGS] if len(captured) > CAPTURE_LENGTH_4DGS else {}
        rows = {"xyz": xyz, "f_dc": f_dc, "f_rest": f_rest, "opacity": opacity, "scaling": scaling,
                "rotation": rotation}
        self.check_rows(rows, source)
        count = xyz.shape[0]
        per_gaussian = {"max_radii2D": max_radii, "xyz_gradient_accum": grad_accum, "denom": denom,
                        "deformation_table": table, "deformation_accum": extras.get("deformation_accum", xyz),
                        **extras.get("buffers", {}), **extras.get("parameters", {})}
        for name, value in per_gaussian.items():
            if not isinstance(value, Tensor) or value.dim() == 0 or value.shape[0] != count:
                got = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise ValueError(f"{source}: {name} is {got}, expected {count} rows")
        missing_lrs = [n for n in extras.get("parameters", {}) if n not in extras.get("parameter_lrs", {})]
        if missing_lrs:
            raise ValueError(f"{source}: no learning rate stored for per-Gaussian parameters {missing_lrs}")
        check_deformation_state(self._deformation, deformation_state, source)
        parameters = extras.get("parameters", {})
        module_groups = self._module_groups()
        unknown_frozen = [n for n in extras.get("frozen", [])
                          if n not in GROUP_ORDER and n not in parameters and n not in module_groups]
        if unknown_frozen:
            raise ValueError(f"{source}: frozen groups {unknown_frozen} do not exist")
        expected_groups = {name: [rows[name].shape] for name in ROW_GROUPS}
        expected_groups["deformation"] = [p.shape for p in self._deformation.get_mlp_parameters()]
        expected_groups["grid"] = [p.shape for p in self._deformation.get_grid_parameters()]
        expected_groups.update({name: [p.shape for p in params] for name, (_, params) in module_groups.items()})
        expected_groups.update({name: [value.shape] for name, value in parameters.items()})
        check_state_by_group_name(optimizer_state, expected_groups, source)

        device = xyz.device if device is None else torch.device(device)
        self.unfreeze(list(self._frozen))
        self._deformation = self._deformation.to(device)
        self._deformation.load_state_dict(deformation_state, strict=True)
        self.set_gaussians(rows, table, extras.get("deformation_accum"), device, source)
        self.active_sh_degree = int(active_sh_degree)
        self.spatial_lr_scale = float(spatial_lr_scale)
        self.set_extras(extras.get("buffers", {}), parameters, extras.get("parameter_lrs", {}), source)
        self.training_setup(opt)
        self.max_radii2D = max_radii.to(device, torch.float32)
        self.xyz_gradient_accum = grad_accum.to(device)
        self.denom = denom.to(device)
        if "deformation_accum" in extras:  # training_setup zeroed it, as in 4DGS
            self._deformation_accum = extras["deformation_accum"].to(device)
        load_state_by_group_name(self.optimizer, optimizer_state, source)
        self.freeze(extras.get("frozen", []))

    def check_rows(self, rows: Mapping[str, Tensor], source: str) -> None:
        """Raise ``ValueError`` unless the built-in per-Gaussian tensors fit this model."""
        count = rows["xyz"].shape[0]
        rest = (self.max_sh_degree + 1) ** 2 - 1
        expected = {"xyz": (count, 3), "f_dc": (count, 1, 3), "f_rest": (count, rest, 3),
                    "opacity": (count, 1), "scaling": (count, 3), "rotation": (count, 4)}
        for name, shape in expected.items():
            got = tuple(rows[name].shape)
            if got != shape:
                hint = ""
                if name == "f_rest" and len(got) == 3:
                    degree = math.isqrt(got[1] + 1) - 1
                    hint = f" (SH degree {degree} in the file, the model has {self.max_sh_degree})"
                raise ValueError(f"{source}: {ROW_GROUPS[name]} has shape {list(got)}, expected {list(shape)}{hint}")

    def set_extras(
        self,
        buffers: Mapping[str, Tensor],
        parameters: Mapping[str, Tensor],
        parameter_lrs: Mapping[str, float],
        source: str,
    ) -> None:
        """Replace all registered per-Gaussian buffers and parameters (e.g. from a checkpoint)."""
        self._extra_buffers, self._extra_params, self._extra_param_lrs = {}, {}, {}
        for name, value in buffers.items():
            self._register_checked(name, value, source, lambda n, v: self.register_gaussian_buffer(n, v))
        for name, value in parameters.items():
            if name not in parameter_lrs:
                raise ValueError(f"{source}: no learning rate stored for per-Gaussian parameter {name!r}")
            self._register_checked(
                name, value, source, lambda n, v: self.register_gaussian_parameter(n, v, parameter_lrs[n])
            )

    @staticmethod
    def _register_checked(name: str, value: Tensor, source: str, register) -> None:
        try:
            register(name, value)
        except ValueError as err:
            raise ValueError(f"{source}: {err}") from None
