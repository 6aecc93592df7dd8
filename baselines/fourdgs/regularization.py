"""HexPlane regularisers with 4DGS's formulas (scene/regulation.py, GaussianModel.compute_regulation).

4DGS's ``compute_regulation`` sums, over every resolution level of the HexPlane:

- ``plane_tv_weight`` x second-difference smoothness of the three *spatial* planes (xy, xz, yz).
  (4DGS names this term "plane TV", but it calls ``compute_plane_smoothness`` on the spatial
  planes; its ``compute_plane_tv`` is defined and never used. We reproduce what it computes.)
- ``time_smoothness_weight`` x the same smoothness on the three *time* planes (xt, yt, zt), whose
  first grid axis (dimension -2) is time.
- ``l1_time_planes_weight`` x mean |1 - plane| over the time planes (planes start at 1, so this
  pulls the time dependence back towards "no change").

``hexplane_regularization`` computes the sum in one autograd node with a hand-written gradient
(a few passes over each plane instead of the ~15 that autograd's slices, differences and their
backward take; with 4DGS's default model the planes hold 36M values and the regularisers were
the largest part of a step's non-raster cost). ``hexplane_regularization_reference`` is the same
sum written with the formulas above, the test oracle (equal to float rounding).

On float32 / float64 CPU planes ``hexplane_regularization`` runs the compiled kernel of
``regularization_kernel.py`` (value and gradient in one pass over the planes; the torch Function
here is its oracle and its fallback: ``REFLOW4DGS_REG_KERNEL=0``, no compiler, other devices).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from baselines.fourdgs import regularization_kernel

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


def _second_difference(plane: Tensor) -> Tensor:
    """[B, C, H-2, W]: plane[h+2] - 2 plane[h+1] + plane[h] along dimension -2."""
    return torch.sub(plane[..., 2:, :] + plane[..., :-2, :], plane[..., 1:-1, :], alpha=2.0)


class _WeightedPlaneRegularisation(torch.autograd.Function):
    """sum_p smooth_w[p] * mean(second difference of p)^2 + l1_w[p] * mean|1 - p|, fused."""

    @staticmethod
    def forward(ctx, smooth_weights: tuple[float, ...], l1_weights: tuple[float, ...], *planes: Tensor) -> Tensor:
        total = planes[0].new_zeros(())
        for plane, smooth, l1 in zip(planes, smooth_weights, l1_weights):
            if smooth != 0 and plane.shape[-2] >= 3:
                second = _second_difference(plane)
                total += smooth * second.square().sum() / second.numel()
            if l1 != 0:
                total += l1 * (plane - 1.0).abs().sum() / plane.numel()
        ctx.save_for_backward(*planes)
        ctx.weights = (smooth_weights, l1_weights)
        return total

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_total: Tensor):
        smooth_weights, l1_weights = ctx.weights
        grads: list[Tensor | None] = []
        for plane, smooth, l1, needed in zip(ctx.saved_tensors, smooth_weights, l1_weights, ctx.needs_input_grad[2:]):
            has_smooth = smooth != 0 and plane.shape[-2] >= 3
            if not needed or not (has_smooth or l1 != 0):
                grads.append(None)
                continue
            grad = torch.zeros_like(plane)
            if has_smooth:
                # d/dp of mean(s^2), s[h] = p[h+2] - 2 p[h+1] + p[h]: scatter 2 s / M back to the 3 rows
                second = _second_difference(plane)
                scaled = second.mul_(grad_total * (2.0 * smooth / second.numel()))
                grad[..., 2:, :] += scaled
                grad[..., :-2, :] += scaled
                grad[..., 1:-1, :].sub_(scaled, alpha=2.0)
            if l1 != 0:
                # d/dp |1 - p| = sign(p - 1) (0 at p = 1, as autograd's abs)
                grad.add_(torch.sign(plane - 1.0), alpha=float(grad_total) * l1 / plane.numel())
            grads.append(grad)
        return (None, None, *grads)


def hexplane_regularization(
    levels: Iterable[Sequence[Tensor]],
    time_smoothness_weight: float,
    l1_time_planes_weight: float,
    plane_tv_weight: float,
) -> Tensor:
    """4DGS's ``compute_regulation`` over the planes of every level (each a sequence of 6 planes)."""
    planes: list[Tensor] = []
    smooth: list[float] = []
    l1: list[float] = []
    device = None
    for level in levels:
        device = level[0].device if len(level) else device
        if len(level) != 6:  # a 3-plane (static) level has no time planes and is skipped by 4DGS
            continue
        for index, plane in enumerate(level):
            if plane.dim() != 4:
                raise ValueError(f"hexplane_regularization: expected [B, C, H, W] planes, got {list(plane.shape)}")
            time_plane = index in TIME_PLANES
            planes.append(plane)
            smooth.append(float(time_smoothness_weight if time_plane else plane_tv_weight))
            l1.append(float(l1_time_planes_weight) if time_plane else 0.0)
    if not planes:  # on the planes' device: the trainer stacks it with the other loss terms
        return torch.zeros((), device=device)
    reason = regularization_kernel.unusable_reason(planes)
    if reason is None:
        return regularization_kernel.weighted_plane_regularisation(smooth, l1, planes)
    regularization_kernel.log_fallback_once(reason)
    return _WeightedPlaneRegularisation.apply(tuple(smooth), tuple(l1), *planes)


def hexplane_regularization_reference(
    levels: Iterable[Sequence[Tensor]],
    time_smoothness_weight: float,
    l1_time_planes_weight: float,
    plane_tv_weight: float,
) -> Tensor:
    """``hexplane_regularization`` written as 4DGS writes it (autograd through the formulas)."""
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
