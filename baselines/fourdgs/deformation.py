"""4DGS's deformation network (scene/deformation.py) with 4DGS's state-dict names.

``DeformNetwork`` (alias ``deform_network``) holds ``timenet`` (kept for the state dict; 4DGS
never calls it), ``deformation_net`` = ``Deformation`` (HexPlane ``grid``, ``feature_out`` and the
``pos/scales/rotations/opacity/shs_deform`` heads) and the positional-encoding buffers
``time_poc``, ``pos_poc``, ``rotation_scaling_poc``, ``opacity_poc``. A ``deformation.pth``
written by 4DGS loads here with ``strict=True`` and ours loads in 4DGS.

What the network computes (4DGS's ``forward_dynamic``): hidden = feature_out(grid(xyz, t)); each
enabled head maps hidden -> a delta added to the pre-activation value (means, log-scales, raw
quaternion, opacity logit, SH). Our interface differs from 4DGS's: ``forward(state, times,
buffers) -> GaussianState`` (see ``DeformationModule``), so a plugin can swap the module.

The layer structure is 4DGS's; the speed-up over 4DGS's module is in the HexPlane lookup (see
``plane_lookup.py``). The heads share their leading ReLU of the trunk output (4DGS applies it
once per head); fusing the heads into one wider matmul was tried and is slower at 100k points,
because its [N, 192] intermediates page-fault on every allocation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.fourdgs.hexplane import HexPlaneField
from baselines.fourdgs.state import GaussianState

# (head name, output width, disabling flag) in 4DGS's order; the SH head always predicts 16
# coefficients (degree 3), as in 4DGS.
SH_HEAD_COEFFICIENTS = 16
_HEADS: tuple[tuple[str, int, str], ...] = (
    ("pos_deform", 3, "no_dx"),
    ("scales_deform", 3, "no_ds"),
    ("rotations_deform", 4, "no_dr"),
    ("opacity_deform", 1, "no_do"),
    ("shs_deform", SH_HEAD_COEFFICIENTS * 3, "no_dshs"),
)

# the GaussianState field each head deforms
HEAD_FIELDS = {"pos_deform": "means", "scales_deform": "log_scales", "rotations_deform": "rotations",
               "opacity_deform": "opacity_logits", "shs_deform": "shs"}

# 4DGS ModelHiddenParams defaults, used for attributes an args object does not define.
HIDDEN_DEFAULTS: dict[str, Any] = {
    "net_width": 64,
    "timebase_pe": 4,
    "defor_depth": 1,
    "posebase_pe": 10,
    "scale_rotation_pe": 2,
    "opacity_pe": 2,
    "timenet_width": 64,
    "timenet_output": 32,
    "bounds": 1.6,
    "plane_tv_weight": 0.0001,
    "time_smoothness_weight": 0.01,
    "l1_time_planes": 0.0001,
    "kplanes_config": {
        "grid_dimensions": 2,
        "input_coordinate_dim": 4,
        "output_coordinate_dim": 32,
        "resolution": [64, 64, 64, 25],
    },
    "multires": [1, 2, 4, 8],
    "no_dx": False,
    "no_grid": False,
    "no_ds": False,
    "no_dr": False,
    "no_do": True,
    "no_dshs": True,
    "empty_voxel": False,
    "grid_pe": 0,
    "static_mlp": False,
    "apply_rotation": False,
    "mlp_precision": "float32",  # ours (4DGS: float32); see mlp_autocast
}


@runtime_checkable
class DeformationModule(Protocol):
    """What ``GaussianModel`` needs from a deformation module (a plugin may supply its own).

    ``forward(state, times [N,1], buffers) -> GaussianState`` maps canonical pre-activation
    Gaussians to time ``times``; ``buffers`` holds the model's registered per-Gaussian buffers
    and parameters and its ``deformation_table`` ([N] bool), rows aligned with ``state``
    (``GaussianModel.deformation_inputs``). 4DGS's network deforms every row. Rows must be deformed
    independently of each other: ``GaussianModel.deform_many`` stacks the state once per time and
    makes one call (adding ``buffers["row_gaussian"]``, [kN] long: the Gaussian each row is, for
    a term a module computes once per Gaussian; and, when its caller says which rows it reads,
    ``buffers["row_used"]``, [kN] bool: a module may return the other rows undeformed). Optimizer groups "deformation" and "grid" are built from
    ``get_mlp_parameters()`` and ``get_grid_parameters()``; optional ``scheduled_groups()`` ->
    {name: (schedule, parameters)} adds groups of the module's own (e.g. a second field at other
    rates: ``GaussianModel.scale_learning_rate(name, ...)``), each on the "deformation" or "grid"
    schedule. Optional: ``passed_through()`` ->
    the state fields the module returns as its input's own tensors without reading them, for any
    input (4DGS's network: the fields of its disabled heads); ``deform_many`` then repeats only
    the other fields and hands these as zero-copy stand-ins (state.stand_in), checking that they
    come back untouched. Optional: ``complete_foreign_state(state) -> state``, called when a
    point_cloud folder is loaded, before its ``deformation.pth`` is checked: a module with more
    parts than 4DGS's network fills in the entries a 4DGS folder lacks (the check stays strict
    for everything else).
    """

    def __call__(
        self, state: GaussianState, times: Tensor, buffers: Mapping[str, Tensor] | None = None
    ) -> GaussianState: ...

    def get_mlp_parameters(self) -> list[nn.Parameter]: ...

    def get_grid_parameters(self) -> list[nn.Parameter]: ...

    def set_aabb(self, xyz_max: Any, xyz_min: Any) -> None: ...

    def compute_regulation(
        self, time_smoothness_weight: float, l1_time_planes_weight: float, plane_tv_weight: float
    ) -> Tensor: ...


def hidden_value(args: Any, name: str) -> Any:
    """``args.name``, else 4DGS's default (so any object with the 4DGS attributes works)."""
    return getattr(args, name, HIDDEN_DEFAULTS[name]) if args is not None else HIDDEN_DEFAULTS[name]


def native_bfloat16_cpu() -> bool:
    """Whether this CPU multiplies bfloat16 natively (AVX512-BF16 or AMX), where oneDNN's bfloat16
    matrix products run 5-10x faster than float32 ones; without it they are emulated and slower."""
    checks = [getattr(torch.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    return any(check is not None and bool(check()) for check in checks)


def mlp_autocast(precision: str, device: torch.device) -> torch.autocast:
    """The autocast context for the deformation MLP's matrix products on ``device``.

    ``bfloat16``: the Linear layers compute in bfloat16 (float32 weights and optimizer state, as
    in mixed-precision training; the grid lookup, the residual additions and everything after the
    heads stay float32). ``auto`` picks bfloat16 only on a CPU that computes it natively: there
    the MLP is most of a training step at real-capture scale (about 40% of a fine iteration at
    33k Gaussians, 240x135, docs/PROFILE.md). ``float32`` is 4DGS's arithmetic.
    """
    use_bf16 = mlp_arithmetic(precision, device) == "bfloat16"
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16)


def mlp_arithmetic(precision: str, device: torch.device) -> str:
    """What ``mlp_precision`` resolves to on ``device``: "bfloat16" or "float32" (``auto`` depends on
    the CPU, so a run records the result: baselines/machine.py)."""
    if precision not in ("auto", "float32", "bfloat16"):
        raise ValueError(f"mlp_precision must be auto, float32 or bfloat16, got {precision!r}")
    native = device.type == "cpu" and native_bfloat16_cpu()
    return "bfloat16" if precision == "bfloat16" or (precision == "auto" and native) else "float32"


def quaternion_multiply(q1: Tensor, q2: Tensor) -> Tensor:
    """Normalised Hamilton product q1 * q2 of [N, 4] (w, x, y, z) quaternions."""
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    product = torch.stack(
        (
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ),
        -1,
    )
    return product / product.norm(dim=-1, keepdim=True)


def _xavier_init(module: nn.Module) -> None:
    # 4DGS's initialize_weights: Xavier-uniform weights, drawn twice when there is a bias (its
    # code re-initialises the weight instead of the bias), biases left at PyTorch's default.
    # Drawing twice keeps the random stream, hence the initial weights for a seed, equal to 4DGS's.
    if isinstance(module, nn.Linear):
        nn.init.xavier_uniform_(module.weight, gain=1)
        if module.bias is not None:
            nn.init.xavier_uniform_(module.weight, gain=1)


def _head(width: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out))


class Deformation(nn.Module):
    """4DGS's ``Deformation``: HexPlane ``grid`` + ``feature_out`` trunk + per-attribute heads.

    ``position_scale`` (ours; 1 = 4DGS): the position head's output is multiplied by it, a
    reparametrisation that lets a plugin make the branch learn at any scene scale as at unit scale
    (``set_position_scale`` keeps the function unchanged). The state dict always holds the
    EFFECTIVE head weights (scale x stored), so checkpoints load in 4DGS and in a model of any
    scale with the same deformation.
    """

    def __init__(self, args: Any, D: int = 8, W: int = 256, grid_pe: int = 0) -> None:
        super().__init__()
        if hidden_value(args, "static_mlp") or hidden_value(args, "empty_voxel"):
            raise ValueError(
                "Deformation: static_mlp and empty_voxel (4DGS options marked 'useless' there) "
                "are not supported; set both to False"
            )
        if grid_pe == 1 or grid_pe < 0:
            raise ValueError(f"Deformation: grid_pe must be 0 or > 1, got {grid_pe}")
        self.D = D
        self.W = W
        self.grid_pe = grid_pe
        self.no_grid = bool(hidden_value(args, "no_grid"))
        self.flags = {flag: bool(hidden_value(args, flag)) for _, _, flag in _HEADS}
        self.apply_rotation = bool(hidden_value(args, "apply_rotation"))
        self.mlp_precision = str(hidden_value(args, "mlp_precision"))
        mlp_autocast(self.mlp_precision, torch.device("cpu"))  # reject an unknown value now
        self.grid = HexPlaneField(
            hidden_value(args, "bounds"), hidden_value(args, "kplanes_config"), hidden_value(args, "multires")
        )
        in_dim = 4 if self.no_grid else self.grid.feat_dim * (3 if grid_pe else 1)
        layers: list[nn.Module] = [nn.Linear(in_dim, W)]
        for _ in range(D - 1):
            layers += [nn.ReLU(), nn.Linear(W, W)]
        self.feature_out = nn.Sequential(*layers)
        for name, out, _ in _HEADS:
            setattr(self, name, _head(W, out))
        self.position_scale = 1.0
        self._register_state_dict_hook(_save_effective_position_head)
        self.register_load_state_dict_pre_hook(_load_effective_position_head)

    def set_position_scale(self, scale: float) -> None:
        """Multiply the position head's output by `scale` from now on, keeping the function as it is
        (its last layer is divided by scale / previous scale)."""
        scale = float(scale)
        if not math.isfinite(scale) or scale <= 0:
            raise ValueError(f"Deformation: position_scale must be finite and > 0, got {scale}")
        if scale == self.position_scale:
            return
        with torch.no_grad():
            last = self.pos_deform[3]
            last.weight.mul_(self.position_scale / scale)
            last.bias.mul_(self.position_scale / scale)
        self.position_scale = scale

    @property
    def get_aabb(self) -> tuple[Tensor, Tensor]:
        return self.grid.get_aabb

    def set_aabb(self, xyz_max: Any, xyz_min: Any) -> None:
        self.grid.set_aabb(xyz_max, xyz_min)

    def active_heads(self) -> list[str]:
        return [name for name, _, flag in _HEADS if not self.flags[flag]]

    def passed_through(self) -> frozenset[str]:
        """State fields `forward` returns as its input's own tensors, unread: those of the disabled
        heads (4DGS's defaults: opacity_logits and shs)."""
        return frozenset(HEAD_FIELDS[name] for name, _, flag in _HEADS if self.flags[flag])

    def hidden(self, means: Tensor, times: Tensor) -> Tensor:
        """[N, W] trunk features of 4DGS's ``query_time``."""
        if self.no_grid:
            # 4DGS's no_grid branch references an undefined variable; this is what it intends.
            features = torch.cat((means, times), 1)
        else:
            features = self.grid(means, times)
            if self.grid_pe > 1:
                scaled = features * self.grid_pe
                features = torch.cat((features, scaled.sin(), scaled.cos()), 1)
        with mlp_autocast(self.mlp_precision, features.device):
            return self.feature_out(features)

    def head_outputs(self, hidden: Tensor) -> dict[str, Tensor]:
        """Outputs of the enabled heads (their leading ReLU of ``hidden`` is computed once)."""
        names = self.active_heads()
        if not names:
            return {}
        outputs = {}
        with mlp_autocast(self.mlp_precision, hidden.device):
            activated = F.relu(hidden)
            for name in names:
                head = getattr(self, name)
                outputs[name] = head[3](F.relu(head[1](activated)))
        # bfloat16 outputs back to float32 (a float64 model stays float64)
        return {name: out.to(torch.promote_types(out.dtype, torch.float32)) for name, out in outputs.items()}

    def forward(self, state: GaussianState, times: Tensor) -> GaussianState:
        deltas = self.head_outputs(self.hidden(state.means, times))
        # 4DGS's mask is 1 without static_mlp/empty_voxel, so value * mask + delta = value + delta.
        if "pos_deform" in deltas:
            step = deltas["pos_deform"] if self.position_scale == 1.0 else self.position_scale * deltas["pos_deform"]
            means = state.means + step
        else:
            means = state.means
        log_scales = state.log_scales + deltas["scales_deform"] if "scales_deform" in deltas else state.log_scales
        rotations = state.rotations
        if "rotations_deform" in deltas:
            if self.apply_rotation:
                rotations = quaternion_multiply(rotations, deltas["rotations_deform"])
            else:
                rotations = rotations + deltas["rotations_deform"]
        opacity = state.opacity_logits
        if "opacity_deform" in deltas:
            opacity = opacity + deltas["opacity_deform"]
        shs = state.shs
        if "shs_deform" in deltas:
            if shs.shape[1] != SH_HEAD_COEFFICIENTS:
                raise ValueError(
                    f"Deformation: shs_deform predicts {SH_HEAD_COEFFICIENTS} SH coefficients (degree 3) as "
                    f"in 4DGS, but the Gaussians have {shs.shape[1]}; use sh_degree 3 or no_dshs=True"
                )
            shs = shs + deltas["shs_deform"].reshape(-1, SH_HEAD_COEFFICIENTS, 3)
        return GaussianState(means, log_scales, rotations, opacity, shs)

    def get_mlp_parameters(self) -> list[nn.Parameter]:
        """Every parameter whose name lacks "grid" (4DGS's rule), in registration order."""
        return [p for name, p in self.named_parameters() if "grid" not in name]

    def get_grid_parameters(self) -> list[nn.Parameter]:
        """Every parameter whose name has "grid": the aabb (never trained) and the planes."""
        return [p for name, p in self.named_parameters() if "grid" in name]


_POSITION_HEAD = ("pos_deform.3.weight", "pos_deform.3.bias")


def _save_effective_position_head(module: Deformation, state_dict: dict, prefix: str, _metadata: Any) -> None:
    """state_dict hook: the position head's effective weights (new tensors: the dict's entries are
    the parameters themselves)."""
    if module.position_scale != 1.0:
        for key in _POSITION_HEAD:
            if prefix + key in state_dict:
                state_dict[prefix + key] = state_dict[prefix + key] * module.position_scale


def _load_effective_position_head(module: Deformation, state_dict: dict, prefix: str, *_: Any) -> None:
    """load_state_dict pre-hook: effective weights -> stored weights at this module's scale."""
    if module.position_scale != 1.0:
        for key in _POSITION_HEAD:
            if prefix + key in state_dict:
                state_dict[prefix + key] = state_dict[prefix + key] / module.position_scale


class DeformNetwork(nn.Module):
    """4DGS's ``deform_network`` with our ``forward(state, times, buffers) -> GaussianState``.

    Args:
        args: any object with 4DGS's ModelHiddenParams attributes (missing ones take 4DGS's
            defaults): net_width, defor_depth, kplanes_config, multires, bounds, no_dx, no_ds,
            no_dr, no_do, no_dshs, no_grid, apply_rotation, grid_pe, timebase_pe, posebase_pe,
            scale_rotation_pe, opacity_pe, timenet_width, timenet_output.
    """

    def __init__(self, args: Any) -> None:
        super().__init__()
        width = int(hidden_value(args, "net_width"))
        timebase_pe = int(hidden_value(args, "timebase_pe"))
        timenet_width = int(hidden_value(args, "timenet_width"))
        timenet_output = int(hidden_value(args, "timenet_output"))
        # Module creation order follows 4DGS so a seed gives 4DGS's initial weights.
        self.timenet = nn.Sequential(
            nn.Linear(2 * timebase_pe + 1, timenet_width), nn.ReLU(), nn.Linear(timenet_width, timenet_output)
        )
        self.deformation_net = Deformation(
            args, D=int(hidden_value(args, "defor_depth")), W=width, grid_pe=int(hidden_value(args, "grid_pe"))
        )
        for name, count in (
            ("time_poc", timebase_pe),
            ("pos_poc", int(hidden_value(args, "posebase_pe"))),
            ("rotation_scaling_poc", int(hidden_value(args, "scale_rotation_pe"))),
            ("opacity_poc", int(hidden_value(args, "opacity_pe"))),
        ):
            self.register_buffer(name, torch.tensor([float(2**i) for i in range(count)], dtype=torch.float32))
        self.apply(_xavier_init)

    def forward(
        self, state: GaussianState, times: Tensor, buffers: Mapping[str, Tensor] | None = None
    ) -> GaussianState:
        """Deform ``state`` (pre-activation, [N] Gaussians) to ``times`` [N, 1]; ``buffers`` unused."""
        n = state.num_gaussians
        if times.dim() == 1:
            times = times.unsqueeze(1)
        if times.shape != (n, 1):
            raise ValueError(f"DeformNetwork: times must be [N, 1] = [{n}, 1], got {list(times.shape)}")
        return self.deformation_net(state, times.to(state.means.dtype))

    @property
    def get_aabb(self) -> tuple[Tensor, Tensor]:
        return self.deformation_net.get_aabb

    def set_aabb(self, xyz_max: Any, xyz_min: Any) -> None:
        self.deformation_net.set_aabb(xyz_max, xyz_min)

    def passed_through(self) -> frozenset[str]:
        """State fields `forward` returns as its input's own tensors, unread (`Deformation.passed_through`)."""
        return self.deformation_net.passed_through()

    def get_mlp_parameters(self) -> list[nn.Parameter]:
        """4DGS's "deformation" optimizer group: deformation_net's non-grid parameters, then timenet."""
        return self.deformation_net.get_mlp_parameters() + list(self.timenet.parameters())

    def get_grid_parameters(self) -> list[nn.Parameter]:
        """4DGS's "grid" optimizer group."""
        return self.deformation_net.get_grid_parameters()

    def compute_regulation(
        self, time_smoothness_weight: float, l1_time_planes_weight: float, plane_tv_weight: float
    ) -> Tensor:
        return self.deformation_net.grid.compute_regulation(
            time_smoothness_weight, l1_time_planes_weight, plane_tv_weight
        )

    def regularization(self, hidden_args: Any) -> Tensor:
        """The HexPlane regularisers weighted by ``hidden_args`` (4DGS's train.py call)."""
        return self.compute_regulation(
            hidden_value(hidden_args, "time_smoothness_weight"),
            hidden_value(hidden_args, "l1_time_planes"),
            hidden_value(hidden_args, "plane_tv_weight"),
        )


deform_network = DeformNetwork


def check_deformation_state(module: nn.Module, state: Mapping[str, Any], source: str, limit: int = 5) -> None:
    """Raise ``ValueError`` unless ``state`` has exactly ``module``'s state-dict keys and shapes.

    The message names ``source`` and lists the first ``limit`` missing, unexpected and
    mis-shaped keys, so a wrong config (e.g. other multires or net_width) is obvious.
    """
    if not isinstance(state, Mapping):
        raise ValueError(f"{source}: deformation state is a {type(state).__name__}, not a state dict")
    expected = module.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    mis_shaped = [
        f"{k} {list(state[k].shape) if isinstance(state[k], Tensor) else type(state[k]).__name__} "
        f"(model: {list(v.shape)})"
        for k, v in expected.items()
        if k in state and (not isinstance(state[k], Tensor) or state[k].shape != v.shape)
    ]
    problems = []
    for label, keys in (("missing", missing), ("unexpected", unexpected), ("wrong shape", mis_shaped)):
        if keys:
            more = f" (+{len(keys) - limit} more)" if len(keys) > limit else ""
            problems.append(f"{label}: {', '.join(keys[:limit])}{more}")
    if problems:
        raise ValueError(f"{source}: deformation state does not fit the model; " + "; ".join(problems))


def load_deformation_state(module: nn.Module, state: Mapping[str, Any], source: str) -> None:
    """Check (see ``check_deformation_state``) then ``load_state_dict(strict=True)``."""
    check_deformation_state(module, state, source)
    module.load_state_dict(state, strict=True)
