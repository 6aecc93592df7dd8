"""Static/dynamic separated deformation (paper section 3.2.2, appendix A.2).

    deformation = SeparatedDeformation(hidden_args, static_decoder="none", zero_init=True)
    model = GaussianModel(sh_degree, hidden_args, deformation=deformation)
    model.set_deformation_table(is_dynamic)      # the labels: 4DGS's "this Gaussian is deformed"

Dynamic Gaussians (deformation table True) go through 4DGS's full HexPlane + delta heads; static
Gaussians never touch the temporal planes, so the deformation cost follows the number of DYNAMIC
Gaussians. The module IS a 4DGS `DeformNetwork` (subclass): with `static_decoder="none"` its
state dict has exactly 4DGS's keys, so a 4DGS `deformation.pth` loads into the dynamic branch and
ours loads in 4DGS.

Static Gaussians are time-invariant, except with "field". The choices (`static_decoder`):
- "none": their stored (canonical) values are used as they are;
- "triplane": the paper's D_s: the dynamic branch's SPATIAL planes (xy, xz, yz, shared, as the
  paper's F_s) are sampled, multiplied per level and decoded by a small MLP into time-invariant
  deltas of position, log-scale and rotation (state-dict keys `static_decoder.*`, beyond 4DGS's);
- "field" (ours): a second 4DGS deformation network over the WHOLE scene box (state-dict keys
  `static_field.*`), at 4DGS's own rates (optimizer groups `static_deformation` / `static_grid`,
  `scheduled_groups`) and regularisers, output layers zeroed: the static Gaussians get the
  baseline's small time-varying corrections (what a casual capture's camera and geometry errors
  ask for), while the dynamic branch keeps its box, rates, windows and anchor. A partner frame
  reads the static rows at its view's time (ReFlowPlugin.partner_shared_rows, deform_many's
  `shared`), so the field runs once per view.

Labels are 4DGS's `_deformation_table` ([N] bool): clone/split/prune keep it in step and it is
saved as `deformation_table.pth`, so labels survive densification and checkpoints for free. A
table that is all True (any 4DGS checkpoint) makes this module equal to 4DGS's.

Temporal windows (ours, with keyframe seeding): when the model carries the per-Gaussian buffer
`reflow_time_center` and parameter `reflow_time_log_scale`, a dynamic Gaussian's opacity is
multiplied by exp(-((t - center) / scale)^2 / 2): it lives around the keyframe it was seeded from.
With `relative_time` such a Gaussian is deformed at tau = t - center (one motion field shared by
every keyframe's copy of the object) and, `anchored`, by D(x, tau) - D(x, 0): it sits EXACTLY
where it was seeded at its own time, whatever the field learns. Without the anchor the field's
value at tau = 0 is free, and a loss that asks for motion at tau != 0 (flow matching) drags the
seeds away from their keyframe through the shared plane cells (measured: training-view
PSNR-dynamic 32.8 -> 19 dB in 300 flow-only steps; docs/REFLOW.md, "The failure ReFlow must fix").

`zero_init` zeroes the last layer of every delta head (deltas start at exactly 0, so dynamic
Gaussians start where the canonical space put them, at every time); 4DGS's Xavier draws happen
first, so the random stream, hence every other initial weight, equals 4DGS's for a seed.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn

from baselines.fourdgs.deformation import DeformNetwork
from baselines.fourdgs.hexplane import PLANE_AXES
from baselines.fourdgs.plane_lookup import PlaneLayout, plane_product_lookup, planes_to_table
from baselines.fourdgs.state import STATE_FIELDS, GaussianState

SPATIAL_PLANE_INDICES = tuple(i for i, axes in enumerate(PLANE_AXES) if 3 not in axes)  # xy, xz, yz
TIME_CENTER = "reflow_time_center"  # [N, 1] buffer: the time a dynamic Gaussian was seeded at
TIME_LOG_SCALE = "reflow_time_log_scale"  # [N, 1] parameter: log of its temporal standard deviation
ALPHA_CUTOFF = 1.0 / 255.0  # the rasterizer skips a Gaussian at a pixel below this alpha


def temporal_window(opacity_logits: Tensor, times: Tensor, centers: Tensor, log_scales: Tensor) -> Tensor:
    """Opacity logits of Gaussians that live around a time: o(t) = o exp(-((t - c) / s)^2 / 2).

    All [M, 1]. The result is clamped to (1e-6, 1 - 1e-6) before the logit, so values and
    gradients stay finite far from the centre.
    """
    window = torch.exp(-0.5 * ((times - centers) / log_scales.exp()) ** 2)
    opacity = (torch.sigmoid(opacity_logits) * window).clamp(1e-6, 1.0 - 1e-6)
    return torch.logit(opacity)


def _zero_heads(network: DeformNetwork) -> None:
    """Zero the last layer of every delta head: the network starts as the identity."""
    for name in ("pos_deform", "scales_deform", "rotations_deform", "opacity_deform", "shs_deform"):
        last = getattr(network.deformation_net, name)[3]
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)


class StaticDecoder(nn.Module):
    """D_s: spatial-plane features -> time-invariant deltas (position 3, log-scale 3, rotation 4).

    Reads the planes of `grid` (a HexPlaneField) without owning them (they are the dynamic
    branch's parameters). Output layer zero-initialised: the decoder starts as the identity.
    """

    def __init__(self, grid: nn.Module, width: int) -> None:
        super().__init__()
        self._grid = [grid]  # not a submodule: the planes belong to the dynamic branch
        levels = len(grid.grids)
        channels = grid.grids[0][0].shape[1]
        planes = [level[i] for level in grid.grids for i in SPATIAL_PLANE_INDICES]
        self.layout = PlaneLayout.build([tuple(p.shape[-2:]) for p in planes],
                                        [PLANE_AXES[i] for i in SPATIAL_PLANE_INDICES] * levels, 3)
        self.net = nn.Sequential(nn.Linear(levels * channels, width), nn.ReLU(), nn.Linear(width, 10))
        nn.init.zeros_(self.net[2].weight)
        nn.init.zeros_(self.net[2].bias)

    def forward(self, means: Tensor) -> Tensor:
        """[N, 10] deltas (dx 3, dlog_scale 3, drotation 4) of static Gaussians at `means` [N, 3]."""
        grid = self._grid[0]
        planes = [level[i] for level in grid.grids for i in SPATIAL_PLANE_INDICES]
        features = plane_product_lookup(planes_to_table(planes), self.layout, grid.normalize(means))
        return self.net(features)


class SeparatedDeformation(DeformNetwork):
    """4DGS's deformation network applied to the dynamic rows only (see the module docstring).

    Args:
        args: 4DGS ModelHiddenParams-like object (as `DeformNetwork`).
        static_decoder: "none" or "triplane".
        zero_init: zero the delta heads' output layers.
        relative_time: Gaussians with a `reflow_time_center` are deformed at t - center.
        anchored: with relative time, deform by D(x, t - center) - D(x, 0): exactly no motion at
            the Gaussian's own time (see the module docstring).
        window_cull: keyframe copies whose temporal window weight at t is below this are not
            deformed (they stay at their seeded place, with their windowed opacity, far below what
            the rasterizer draws); 0 deforms every dynamic Gaussian.
    """

    def __init__(self, args: Any, static_decoder: str = "none", zero_init: bool = True,
                 relative_time: bool = True, anchored: bool = True, window_cull: float = 0.0) -> None:
        super().__init__(args)
        self.relative_time = relative_time
        self.anchored = anchored
        self.window_cull = float(window_cull)
        if static_decoder not in ("none", "triplane", "field"):
            raise ValueError(f"static_decoder must be 'none', 'triplane' or 'field', got {static_decoder!r}")
        if zero_init:
            _zero_heads(self)
        self.static_decoder = (StaticDecoder(self.deformation_net.grid, self.deformation_net.W)
                               if static_decoder == "triplane" else None)
        self.static_field = DeformNetwork(args) if static_decoder == "field" else None
        if self.static_field is not None:
            _zero_heads(self.static_field)

    def forward(self, state: GaussianState, times: Tensor, buffers: Mapping[str, Tensor] | None = None) -> GaussianState:
        """Deform the rows whose `buffers["deformation_table"]` is True (all rows without a table)."""
        n = state.num_gaussians
        if times.dim() == 1:
            times = times.unsqueeze(1)
        table = (buffers or {}).get("deformation_table")
        if table is None:
            table = torch.ones(n, dtype=torch.bool, device=state.means.device)
        if table.shape != (n,):
            raise ValueError(f"SeparatedDeformation: deformation_table must be [{n}], got {list(table.shape)}")
        out = state
        if self.static_decoder is not None and not bool(table.all()):
            out = self._decode_static(out, (~table).nonzero().squeeze(1))
        if self.static_field is not None and not bool(table.all()):
            out = self._deform_static(out, times, table, (buffers or {}).get("row_used"))
        dynamic = table.nonzero().squeeze(1)
        if dynamic.numel() == 0:
            return out
        centers, log_scales = (buffers or {}).get(TIME_CENTER), (buffers or {}).get(TIME_LOG_SCALE)
        # Keyframe seeds are deformed in their own time: tau = t - t_k, on 4DGS's whole [-1, 1] axis
        field_times = times if centers is None or not self.relative_time else times - centers.to(times.dtype)
        relative = centers is not None and self.relative_time
        deformed = dynamic
        if self.window_cull > 0 and centers is not None and log_scales is not None:
            deformed = self._inside_windows(dynamic, times, centers, log_scales)
        used = (buffers or {}).get("row_used")
        if used is not None:  # rows the caller does not read stay canonical (GaussianModel.deform_many)
            deformed = deformed[used[deformed]]
        if deformed.numel() == n and not relative:
            out = super().forward(out, field_times)
        elif deformed.numel() > 0:  # none alive at t (every copy culled): nothing to deform
            # the fields the network passes through (SH, opacity) are not gathered: stand-ins
            passed = super().passed_through()
            rows = out.index(deformed, stand_ins=passed)
            if relative and self.anchored:
                row_gaussian = (buffers or {}).get("row_gaussian")
                moved = self._anchored_forward(rows, field_times[deformed],
                                               None if row_gaussian is None else row_gaussian[deformed])
            else:
                moved = super().forward(rows, field_times[deformed])
            for name in passed:
                if getattr(moved, name) is not getattr(rows, name):
                    raise RuntimeError(f"SeparatedDeformation: the network changed {name}, which its "
                                       "passed_through() says it returns untouched")
            # A field the network passed through (4DGS's disabled heads: SH, opacity) keeps `out`'s
            # tensor: no copy forward, no scatter of a [N, 16, 3] gradient backward (same values).
            out = GaussianState(*(
                getattr(out, name) if getattr(moved, name) is getattr(rows, name)
                else getattr(out, name).index_copy(0, deformed, getattr(moved, name))
                for name in STATE_FIELDS))
        if centers is not None and log_scales is not None:
            logits = temporal_window(out.opacity_logits[dynamic], times[dynamic].to(centers.dtype),
                                     centers[dynamic], log_scales[dynamic])
            out = out.replace(opacity_logits=out.opacity_logits.index_copy(0, dynamic, logits))
        return out

    def alive_at(self, time: float, buffers: Mapping[str, Tensor]) -> Tensor | None:
        """[N] bool: every static Gaussian and the dynamic ones `forward` deforms at `time`, i.e. all
        but those whose temporal window culls them there; None without windows (all alive).

        A culled Gaussian's opacity at `time` is below window_cull (ReFlow's 1e-3 < 1/255, the
        rasterizer's alpha cutoff), so no view at that time shows it: ReFlow's partner frames need not
        deform it. With a cull above 1/255 that would not hold, and every row counts as alive (None).
        """
        table = buffers.get("deformation_table")
        centers, log_scales = buffers.get(TIME_CENTER), buffers.get(TIME_LOG_SCALE)
        if not 0 < self.window_cull <= ALPHA_CUTOFF or table is None or centers is None or log_scales is None:
            return None
        times = torch.full((table.shape[0], 1), float(time), dtype=centers.dtype, device=centers.device)
        alive = ~table
        alive[self._inside_windows(table.nonzero().squeeze(1), times, centers, log_scales)] = True
        return alive

    def _inside_windows(self, dynamic: Tensor, times: Tensor, centers: Tensor, log_scales: Tensor) -> Tensor:
        """The rows of `dynamic` whose temporal window weight at their time is >= window_cull."""
        with torch.no_grad():
            z = (times[dynamic].to(centers.dtype) - centers[dynamic]) / log_scales[dynamic].exp()
            weight = torch.exp(-0.5 * z.square()).squeeze(1)
        return dynamic[weight >= self.window_cull]

    def _anchored_forward(self, state: GaussianState, taus: Tensor, gaussians: Tensor | None = None) -> GaussianState:
        """state deformed by D(x, tau) - D(x, 0) ([M] rows, taus [M, 1]): one network call.

        D(x, 0) depends on the Gaussian only (its canonical centre), so with `gaussians` ([M]
        long: the Gaussian each row is; `GaussianModel.deform_many` stacks a view and its partner)
        it is evaluated once per distinct Gaussian: M + U rows instead of 2M (U <= M distinct).
        Rotations take the additive difference (4DGS's default `apply_rotation=False` adds its
        rotation delta, so this is exact there).
        """
        m = state.num_gaussians
        rows = torch.arange(m, device=taus.device)
        if gaussians is None:
            zero_rows, back = rows, rows
        else:
            # one representative row per distinct Gaussian (the lowest: deterministic), and each row's one
            distinct, back = torch.unique(gaussians, return_inverse=True)
            zero_rows = torch.full((distinct.numel(),), m, device=taus.device).scatter_reduce(
                0, back, rows, reduce="amin")
        u = zero_rows.numel()
        doubled = state.index(torch.cat((rows, zero_rows)), stand_ins=super().passed_through())
        both = super().forward(doubled, torch.cat((taus, taus.new_zeros(u, 1))))

        def moved(name: str) -> Tensor:
            value = getattr(both, name)
            if value is getattr(doubled, name):
                # passed through: at - zero = 0 exactly, so `state`'s own tensor (the identity
                # keeps the forward and backward work off SH and opacity)
                return getattr(state, name)
            zero = value[m:] if gaussians is None else value[m:][back]
            return getattr(state, name) + (value[:m] - zero)

        return GaussianState(*(moved(name) for name in STATE_FIELDS))

    def passed_through(self) -> frozenset[str]:
        """Fields `forward` returns untouched whatever the input (GaussianModel.deform_many repeats
        only the others): the network's, less the opacity (temporal windows scale it) and the
        fields the static decoder moves."""
        changed = {"opacity_logits"}
        if self.static_decoder is not None:
            changed |= {"means", "log_scales", "rotations"}
        if self.static_field is not None:
            changed |= set(STATE_FIELDS) - self.static_field.passed_through()
        return super().passed_through() - changed

    def _deform_static(self, state: GaussianState, times: Tensor, table: Tensor, used: Tensor | None) -> GaussianState:
        """Static rows through `static_field` at their (absolute) times; rows the caller does not read skipped."""
        static = ~table if used is None else ~table & used
        rows = static.nonzero().squeeze(1)
        if rows.numel() == 0:
            return state
        passed = self.static_field.passed_through()
        moved = self.static_field(state.index(rows, stand_ins=passed), times[rows])
        return GaussianState(*(
            getattr(state, name) if name in passed else getattr(state, name).index_copy(0, rows, getattr(moved, name))
            for name in STATE_FIELDS))

    def _decode_static(self, state: GaussianState, rows: Tensor) -> GaussianState:
        deltas = self.static_decoder(state.means[rows])
        return state.replace(
            means=state.means.index_add(0, rows, deltas[:, 0:3]),
            log_scales=state.log_scales.index_add(0, rows, deltas[:, 3:6]),
            rotations=state.rotations.index_add(0, rows, deltas[:, 6:10]),
        )

    def complete_foreign_state(self, state: Mapping[str, Any]) -> Mapping[str, Any]:
        """A 4DGS `deformation.pth` (this module's keys less the static branch's) made loadable.

        Called by the host before it checks a loaded point_cloud folder's deformation state. A
        state that holds any static-branch key is returned unchanged and checked as it is (a
        ReFlow folder, or a broken one). Otherwise the static branch is filled in: the field
        (`static_field.*`) becomes a copy of the 4DGS network itself, so the upgraded static
        Gaussians keep 4DGS's motion and need no baking; the triplane decoder keeps its
        zero-initialised output layer (the identity). Without a static branch: unchanged.
        """
        branch = "static_field." if self.static_field is not None else (
            "static_decoder." if self.static_decoder is not None else None)
        if branch is None or any(str(k).startswith(branch) for k in state):
            return state
        completed = dict(state)
        if self.static_field is not None:
            completed.update({branch + k: v for k, v in state.items() if k in self.static_field.state_dict()})
        else:
            completed.update({k: v.detach().clone() for k, v in self.state_dict().items() if k.startswith(branch)})
        return completed

    def get_mlp_parameters(self) -> list[nn.Parameter]:
        """4DGS's "deformation" group, plus the static decoder's MLP."""
        extra = list(self.static_decoder.parameters()) if self.static_decoder is not None else []
        return super().get_mlp_parameters() + extra

    def get_grid_parameters(self) -> list[nn.Parameter]:
        """4DGS's "grid" group (the static decoder reads these planes, it owns none)."""
        return self.deformation_net.get_grid_parameters()

    def scheduled_groups(self) -> dict[str, tuple[str, list[nn.Parameter]]]:
        """The static field's own optimizer groups (4DGS's rates: the dynamic multiplier scales the
        "deformation" and "grid" groups only); none without it."""
        if self.static_field is None:
            return {}
        return {"static_deformation": ("deformation", self.static_field.get_mlp_parameters()),
                "static_grid": ("grid", self.static_field.get_grid_parameters())}

    def set_aabb(self, xyz_max: Any, xyz_min: Any) -> None:
        """The host's box (every point): both fields; `fit_box` then narrows the dynamic branch's."""
        super().set_aabb(xyz_max, xyz_min)
        if self.static_field is not None:
            self.static_field.set_aabb(xyz_max, xyz_min)

    def compute_regulation(self, time_smoothness_weight: float, l1_time_planes_weight: float,
                           plane_tv_weight: float) -> Tensor:
        """4DGS's HexPlane regularisers of the dynamic branch, plus the static field's."""
        total = super().compute_regulation(time_smoothness_weight, l1_time_planes_weight, plane_tv_weight)
        if self.static_field is not None:
            total = total + self.static_field.compute_regulation(time_smoothness_weight, l1_time_planes_weight,
                                                                 plane_tv_weight)
        return total

    def fit_box(self, points: Tensor, margin: float) -> None:
        """Set the HexPlane box to `points`' box grown by `margin` x its size per side.

        Called with the DYNAMIC points so the planes' resolution is spent on what moves (the
        host sets the box from every point). A flat axis gets the largest axis' size.
        """
        low, high = points.min(0).values, points.max(0).values
        size = high - low
        size = torch.where(size > 1e-6 * size.max().clamp_min(1e-12), size, size.max().clamp_min(1e-3))
        centre = 0.5 * (low + high)
        half = 0.5 * size * (1.0 + 2.0 * margin)
        super().set_aabb(centre + half, centre - half)
