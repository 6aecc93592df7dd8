"""HexPlane feature field with 4DGS semantics and parameter names (scene/hexplane.py).

A level holds six planes, one per pair of the 4 coordinates (x, y, z, t) in the order
``itertools.combinations(range(4), 2)``: xy, xz, xt, yz, yt, zt. The plane for the pair (a, b)
has shape [1, C, res[b], res[a]], so ``grid_sample`` coordinates (u, v) = (coord_a, coord_b).
A point's feature at one level is the elementwise product of its six bilinear samples
(``align_corners=True``, border padding); levels are concatenated. Spatial resolutions are
multiplied by the level's multiplier, the time resolution is not. Spatial planes start
uniform in [0.1, 0.5], planes containing time start at 1, so at initialisation the feature
does not depend on t.

Coordinates follow 4DGS exactly: points are mapped with ``(p - aabb[0]) * 2 / (aabb[1] -
aabb[0]) - 1`` where ``aabb = [[max], [min]]`` (so max -> -1, min -> +1), and times are used
as given (t in [0, 1] addresses the upper half of the time axis).

Speed (why the lookup is not ``F.grid_sample``): on CPU, ``grid_sample``'s backward is a
single-threaded per-channel scatter and dominates a 4DGS training step. Here a plane is viewed
as a channels-last table [H*W, C] and a bilinear sample is a 4-row weighted ``embedding_bag``
(one fused, vectorised kernel); the backward re-uses ``embedding_bag`` on the rows sorted by
cell for the table gradient, and on derivative weights for the coordinate gradient. The
result equals ``grid_sample`` to float rounding (tests check values and gradients).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from baselines.fourdgs.regularization import hexplane_regularization

PLANE_AXES: tuple[tuple[int, int], ...] = tuple(itertools.combinations(range(4), 2))


# --------------------------------------------------------------------------------------------
# Bilinear lookup on a channels-last table.
class _BilinearTableSample(torch.autograd.Function):
    """out[n] = sum_k w_k(n) * table[base[n] + shift_k], the 4 corners of a bilinear sample.

    Differentiable in ``table`` [H*W, C] and the fractional offsets ``fx``, ``fy`` [N]; ``base``
    [N] (long, the top-left cell) is not. ``row_step`` is W (or 0 when H == 1), ``col_step`` 1
    (or 0 when W == 1), so a corner that would fall outside the plane always has weight 0.
    """

    @staticmethod
    def forward(ctx, table: Tensor, base: Tensor, fx: Tensor, fy: Tensor, col_step: int, row_step: int):
        gx, gy = 1.0 - fx, 1.0 - fy
        corners = torch.stack((base, base + col_step, base + row_step, base + (col_step + row_step)), 1)
        weights = torch.stack((gx * gy, fx * gy, gx * fy, fx * fy), 1)
        out = F.embedding_bag(corners, table, per_sample_weights=weights, mode="sum")
        ctx.save_for_backward(table, corners, fx, fy)
        ctx.steps = (col_step, row_step)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):
        table, corners, fx, fy = ctx.saved_tensors
        col_step, row_step = ctx.steps
        grad_out = grad_out.contiguous()
        grad_table = grad_fx = grad_fy = None
        gx, gy = 1.0 - fx, 1.0 - fy
        if ctx.needs_input_grad[0]:
            grad_table = _scatter_corners(
                grad_out, corners[:, 0], (gx * gy, fx * gy, gx * fy, fx * fy),
                (0, col_step, row_step, col_step + row_step), table.shape[0],
            )
        if ctx.needs_input_grad[2]:
            d_weights = torch.stack((-gy, gy, -fy, fy), 1)
            d_sample = F.embedding_bag(corners, table, per_sample_weights=d_weights, mode="sum")
            grad_fx = (d_sample * grad_out).sum(1)
        if ctx.needs_input_grad[3]:
            d_weights = torch.stack((-gx, -fx, gx, fx), 1)
            d_sample = F.embedding_bag(corners, table, per_sample_weights=d_weights, mode="sum")
            grad_fy = (d_sample * grad_out).sum(1)
        return grad_table, None, grad_fx, grad_fy, None, None


def _scatter_corners(
    grad_out: Tensor, base: Tensor, weights: Sequence[Tensor], shifts: Sequence[int], num_cells: int
) -> Tensor:
    """grad_table[base[n] + shift_k] += weights_k[n] * grad_out[n], summed over n and k.

    Points are grouped by their top-left cell once (one sort of N keys); each corner is then a
    bag-per-cell ``embedding_bag`` over ``grad_out`` whose result is shifted by the corner's
    offset. This avoids both an [N, 4, C] intermediate and a serial index_add.
    """
    order = torch.argsort(base)
    counts = torch.bincount(base, minlength=num_cells)
    offsets = torch.cumsum(counts, 0) - counts
    grad_table = grad_out.new_zeros(num_cells, grad_out.shape[1])
    for weight, shift in zip(weights, shifts):
        per_cell = F.embedding_bag(order, grad_out, offsets, per_sample_weights=weight[order], mode="sum")
        if shift == 0:
            grad_table += per_cell
        else:
            grad_table[shift:] += per_cell[: num_cells - shift]
    return grad_table


def _axis_lookup(coord: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Top-left index [N] (long) and fractional offset [N] of ``align_corners=True`` sampling.

    Border padding: coordinates are clamped to the grid, and (as in ``grid_sample``) a clamped
    coordinate gets no gradient.
    """
    scaled = (coord + 1.0) * (0.5 * (size - 1))
    inside = (scaled > 0) & (scaled < size - 1)
    clamped = torch.where(inside, scaled, scaled.detach().clamp(0, size - 1))
    index = clamped.detach().floor().clamp_(max=max(size - 2, 0))
    return index.long(), clamped - index


def sample_plane(plane: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear sample of a [1, C, H, W] plane at (u, v) in [-1, 1] -> [N, C].

    Equals ``F.grid_sample(plane, grid, mode='bilinear', padding_mode='border',
    align_corners=True)`` with grid = stack(u, v) (u indexes W, v indexes H).
    """
    _, _, height, width = plane.shape
    ix, fx = _axis_lookup(u, width)
    iy, fy = _axis_lookup(v, height)
    return _sample_table(plane, iy * width + ix, fx, fy)


def _sample_table(plane: Tensor, base: Tensor, fx: Tensor, fy: Tensor) -> Tensor:
    """Bilinear samples [N, C] of a [1, C, H, W] plane at top-left cells ``base`` + offsets."""
    _, channels, height, width = plane.shape
    table = plane.reshape(channels, height * width).t().contiguous()
    return _BilinearTableSample.apply(
        table, base, fx, fy, 1 if width > 1 else 0, width if height > 1 else 0
    )


# --------------------------------------------------------------------------------------------
def _init_level(config: Mapping[str, Any], a: float = 0.1, b: float = 0.5) -> nn.ParameterList:
    """Six planes of one level: uniform(a, b), time planes set to 1 (4DGS's init_grid_param)."""
    resolution = config["resolution"]
    planes = nn.ParameterList()
    for axes in PLANE_AXES:
        shape = [1, config["output_coordinate_dim"]] + [resolution[i] for i in axes[::-1]]
        plane = nn.Parameter(torch.empty(shape))
        if 3 in axes:
            nn.init.ones_(plane)
        else:
            nn.init.uniform_(plane, a=a, b=b)
        planes.append(plane)
    return planes


def _check_plane_config(planeconfig: Mapping[str, Any], multires: Sequence[int]) -> None:
    for key in ("grid_dimensions", "input_coordinate_dim", "output_coordinate_dim", "resolution"):
        if key not in planeconfig:
            raise ValueError(f"kplanes_config: missing key {key!r}")
    if planeconfig["grid_dimensions"] != 2:
        raise ValueError(f"kplanes_config['grid_dimensions'] must be 2, got {planeconfig['grid_dimensions']}")
    if planeconfig["input_coordinate_dim"] != 4:
        raise ValueError(
            f"kplanes_config['input_coordinate_dim'] must be 4 (x, y, z, t), got {planeconfig['input_coordinate_dim']}"
        )
    resolution = list(planeconfig["resolution"])
    if len(resolution) != 4 or any(int(r) != r or r < 1 for r in resolution):
        raise ValueError(f"kplanes_config['resolution'] must be 4 positive integers, got {resolution}")
    channels = planeconfig["output_coordinate_dim"]
    if int(channels) != channels or channels < 1:
        raise ValueError(f"kplanes_config['output_coordinate_dim'] must be a positive integer, got {channels}")
    if len(multires) == 0 or any(int(m) != m or m < 1 for m in multires):
        raise ValueError(f"multires must be a non-empty list of positive integers, got {list(multires)}")


class HexPlaneField(nn.Module):
    """Multi-resolution HexPlane: ``forward(pts [N,3], timestamps [N,1]) -> [N, feat_dim]``.

    Args:
        bounds: initial half-size of the box (aabb = [[b,b,b], [-b,-b,-b]]) until ``set_aabb``.
        planeconfig: 4DGS ``kplanes_config`` (grid_dimensions 2, input_coordinate_dim 4,
            output_coordinate_dim C, resolution [X, Y, Z, T]).
        multires: spatial resolution multipliers, one level each.
    """

    def __init__(self, bounds: float, planeconfig: Mapping[str, Any], multires: Sequence[int]) -> None:
        super().__init__()
        _check_plane_config(planeconfig, multires)
        bounds = float(bounds)
        self.aabb = nn.Parameter(
            torch.tensor([[bounds] * 3, [-bounds] * 3], dtype=torch.float32), requires_grad=False
        )
        self.grid_config = [dict(planeconfig)]
        self.multiscale_res_multipliers = [int(m) for m in multires]
        self.concat_features = True
        self.grids = nn.ModuleList()
        self.feat_dim = 0
        for multiplier in self.multiscale_res_multipliers:
            config = dict(self.grid_config[0])
            resolution = list(config["resolution"])
            config["resolution"] = [r * multiplier for r in resolution[:3]] + resolution[3:]
            level = _init_level(config)
            self.feat_dim += level[-1].shape[1]
            self.grids.append(level)

    @property
    def get_aabb(self) -> tuple[Tensor, Tensor]:
        """(xyz_max [3], xyz_min [3]), 4DGS's property name."""
        return self.aabb[0], self.aabb[1]

    def set_aabb(self, xyz_max: Any, xyz_min: Any) -> None:
        """Set the box the spatial coordinates are normalised with (in place, same device)."""
        box = torch.stack(
            [torch.as_tensor(xyz_max, dtype=torch.float32).reshape(-1),
             torch.as_tensor(xyz_min, dtype=torch.float32).reshape(-1)]
        )
        if box.shape != (2, 3):
            raise ValueError(f"set_aabb: xyz_max and xyz_min must have 3 values each, got {list(box.shape)}")
        if not torch.isfinite(box).all():
            raise ValueError(f"set_aabb: non-finite bounds {box.tolist()}")
        flat = (box[0] - box[1]) == 0
        if flat.any():
            axes = [a for a, f in zip("xyz", flat.tolist()) if f]
            raise ValueError(f"set_aabb: empty extent along axis {', '.join(axes)} (max == min)")
        with torch.no_grad():
            self.aabb.copy_(box.to(self.aabb.device, self.aabb.dtype))

    def normalize(self, pts: Tensor) -> Tensor:
        """Map points into the plane coordinates (4DGS's normalize_aabb)."""
        return (pts - self.aabb[0]) * (2.0 / (self.aabb[1] - self.aabb[0])) - 1.0

    def forward(self, pts: Tensor, timestamps: Tensor) -> Tensor:
        if pts.dim() != 2 or pts.shape[1] != 3:
            raise ValueError(f"HexPlaneField: pts must be [N, 3], got {list(pts.shape)}")
        if timestamps.shape != (pts.shape[0], 1):
            raise ValueError(
                f"HexPlaneField: timestamps must be [N, 1] = [{pts.shape[0]}, 1], got {list(timestamps.shape)}"
            )
        if not bool(torch.isfinite(pts).all()):
            raise ValueError("HexPlaneField: non-finite point coordinates (NaN or inf in the means)")
        coords = torch.cat((self.normalize(pts), timestamps.to(pts.dtype)), 1).unbind(1)
        # Axes are shared by 3 planes per level and time by every level: compute each lookup once.
        lookups: dict[tuple[int, int], tuple[Tensor, Tensor]] = {}

        def axis(i: int, size: int) -> tuple[Tensor, Tensor]:
            if (i, size) not in lookups:
                lookups[(i, size)] = _axis_lookup(coords[i], size)
            return lookups[(i, size)]

        features = []
        for level in self.grids:
            product = None
            for (a, b), plane in zip(PLANE_AXES, level):
                _, channels, height, width = plane.shape
                ix, fx = axis(a, width)
                iy, fy = axis(b, height)
                sample = _sample_table(plane, iy * width + ix, fx, fy)
                product = sample if product is None else product * sample
            features.append(product)
        return torch.cat(features, 1)

    def compute_regulation(
        self, time_smoothness_weight: float, l1_time_planes_weight: float, plane_tv_weight: float
    ) -> Tensor:
        """4DGS's plane regularisers (see ``regularization.py``)."""
        return hexplane_regularization(
            self.grids, time_smoothness_weight, l1_time_planes_weight, plane_tv_weight
        )
