"""HexPlane regularisers with 4DGS's formulas (scene/regulation.py, GaussianModel.compute_regulation).

4DGS's ``compute_regulation`` sums, over every resolution level of the HexPlane:

- ``plane_tv_weight`` x second-difference smoothness of the three *spatial* planes (xy, xz, yz).
  (4DGS names this term "plane TV", but it calls ``compute_plane_smoothness`` on the spatial
  planes; its ``compute_plane_tv`` is defined and never used. We reproduce what it computes.)
- ``time_smoothness_weight`` x the same smoothness on the three *time* planes (xt, yt, zt), whose
  first grid axis (dimension -2) is time.
- ``l1_time_planes_weight`` x mean |1 - plane| over the time planes (planes start at 1, so this
  pulls the time dependence back towards "no change").
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import Tensor

# Plane order of a 4D HexPlane level: itertools.combinations(range(4), 2) ->
# (x,y) (x,z) (x,t) (y,z) (y,t) (z,t).
SPATIAL_PLANES: tuple[int, ...] = (0, 1, 3)
TIME_PLANES: tuple[int, ...] = (2, 4, 5)


def plane_smoothness(plane: Tensor) -> Tensor:
    """Mean squared second difference along dimension -2 of a [B, C, H, W] plane."""
    if plane.dim() != 4:
        raise ValueError(f"plane_smoothness: expected a [B, C, H, W] plane, got {list(plane.shape)}")
    if plane.shape[-2] < 3:
        # A second difference needs 3 samples; 4DGS would return NaN (mean of nothing).
        return plane.new_zeros(())
    first = plane[..., 1:, :] - plane[..., :-1, :]
    second = first[..., 1:, :] - first[..., :-1, :]
    return second.square().mean()


def plane_l1_from_one(plane: Tensor) -> Tensor:
    """Mean |1 - plane|."""
    return (1.0 - plane).abs().mean()


def hexplane_regularization(
    levels: Iterable[Sequence[Tensor]],
    time_smoothness_weight: float,
    l1_time_planes_weight: float,
    plane_tv_weight: float,
) -> Tensor:
    """4DGS's ``compute_regulation`` over the planes of every level (each a sequence of 6 planes)."""
    spatial: Tensor | float = 0.0
    temporal: Tensor | float = 0.0
    l1: Tensor | float = 0.0
    reference: Tensor | None = None
    for planes in levels:
        if len(planes) != 6:  # a 3-plane (static) level has no time planes and is skipped by 4DGS
            continue
        reference = planes[0]
        for i in SPATIAL_PLANES:
            spatial = spatial + plane_smoothness(planes[i])
        for i in TIME_PLANES:
            temporal = temporal + plane_smoothness(planes[i])
            l1 = l1 + plane_l1_from_one(planes[i])
    if reference is None:
        return torch.zeros(())
    return plane_tv_weight * spatial + time_smoothness_weight * temporal + l1_time_planes_weight * l1
