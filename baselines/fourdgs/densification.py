"""4DGS's densify / prune / opacity-reset schedule (the ``with torch.no_grad()`` block of train.py).

Per iteration (stage-local, starting at 1 in each stage as in 4DGS), while
``iteration < densify_until_iter``:

1. max screen radii and view-space gradient statistics of the visible Gaussians are updated;
2. thresholds: coarse stage uses ``*_coarse``; the fine stage interpolates linearly from
   ``*_fine_init`` (iteration 0) towards ``densify_grad_threshold_after`` /
   ``opacity_threshold_fine_after`` (at ``densify_until_iter``);
3. densify (clone + split) when ``iteration > densify_from_iter``, ``iteration %
   densification_interval == 0`` and there are fewer than 360 000 Gaussians;
4. prune when ``iteration > pruning_from_iter``, ``iteration % pruning_interval == 0`` and
   there are MORE than 200 000 Gaussians (4DGS prunes large models only); the screen-size
   criterion (20 px) applies once ``iteration > opacity_reset_interval``;
5. opacity reset when ``iteration % opacity_reset_interval == 0``.

Ours: a ``FinalStretch`` (final_stretch.py) may forbid steps 3-5 near a saved iteration; the
record lists what was skipped.

4DGS's ``add_point``/``grow`` branch is not reproduced: ``GaussianModel.grow`` does not exist in
4DGS, so that branch cannot run there either.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from baselines.fourdgs.final_stretch import FinalStretch
from baselines.fourdgs.gaussian_model import GaussianModel

DENSIFY_MAX_GAUSSIANS = 360_000
PRUNE_MIN_GAUSSIANS = 200_000
SCREEN_SIZE_THRESHOLD = 20


@dataclass
class DensificationRecord:
    """What one ``densification_step`` did (for logging)."""

    iteration: int
    stats_updated: bool = False
    densify_ran: bool = False
    cloned: int = 0  # Gaussians added by cloning
    split: int = 0  # Gaussians replaced by 2 smaller ones each
    prune_ran: bool = False
    pruned: int = 0
    opacity_reset: bool = False
    densify_threshold: float | None = None
    opacity_threshold: float | None = None
    num_gaussians: int = 0
    skipped: list[str] = field(default_factory=list)  # steps due but forbidden by the final-stretch rule


def densification_thresholds(opt: Any, iteration: int, stage: str) -> tuple[float, float]:
    """(gradient threshold, opacity threshold) of 4DGS for ``stage`` at ``iteration``."""
    if stage == "coarse":
        return float(opt.densify_grad_threshold_coarse), float(opt.opacity_threshold_coarse)
    if stage != "fine":
        raise ValueError(f"stage must be 'coarse' or 'fine', got {stage!r}")
    until = opt.densify_until_iter
    grad = opt.densify_grad_threshold_fine_init - iteration * (
        opt.densify_grad_threshold_fine_init - opt.densify_grad_threshold_after
    ) / until
    opacity = opt.opacity_threshold_fine_init - iteration * (
        opt.opacity_threshold_fine_init - opt.opacity_threshold_fine_after
    ) / until
    return float(grad), float(opacity)


@torch.no_grad()
def densification_step(
    model: GaussianModel,
    opt: Any,
    iteration: int,
    stage: str,
    cameras_extent: float,
    visible: Tensor,
    radii: Tensor,
    means2d_grad: Tensor,
    width: int,
    height: int,
    max_gaussians: int = DENSIFY_MAX_GAUSSIANS,
    prune_min_gaussians: int = PRUNE_MIN_GAUSSIANS,
    protect: Tensor | None = None,
    stretch: FinalStretch | None = None,
) -> DensificationRecord:
    """Run 4DGS's densification block for one iteration (call after backward, before the step).

    Args:
        visible: [N] bool, visible in any view of the batch.
        radii: [N] max screen radius in pixels over the batch's views.
        means2d_grad: [N, 2] gradient of the loss w.r.t. the projected means, pixel units,
            summed over the batch's views.
        width, height: image size (converts the gradient to 4DGS's NDC units).
        max_gaussians, prune_min_gaussians: 4DGS's 360 000 cap and 200 000 floor.
        protect: [N] bool, Gaussians never pruned this iteration (ours: the plugins'
            `protected_gaussians`); clones and split children of a protected Gaussian are
            protected too.
        stretch: the steps the final-stretch rule allows this iteration (default: all).
    """
    stretch = stretch or FinalStretch()
    record = DensificationRecord(iteration=iteration, num_gaussians=model.num_gaussians)
    if iteration >= opt.densify_until_iter:
        return record
    count = model.num_gaussians
    if visible.shape != (count,) or radii.shape != (count,):
        raise ValueError(
            f"densification_step: visible and radii must be [{count}], "
            f"got {list(visible.shape)} and {list(radii.shape)}"
        )
    if protect is not None and protect.shape != (count,):
        raise ValueError(f"densification_step: protect must be [{count}] bool, got {list(protect.shape)}")
    model.update_max_radii(radii, visible)
    model.add_densification_stats(means2d_grad, visible, width, height)
    record.stats_updated = True

    grad_threshold, opacity_threshold = densification_thresholds(opt, iteration, stage)
    record.densify_threshold, record.opacity_threshold = grad_threshold, opacity_threshold
    size_threshold = SCREEN_SIZE_THRESHOLD if iteration > opt.opacity_reset_interval else None
    densify_due = (
        iteration > opt.densify_from_iter
        and iteration % opt.densification_interval == 0
        and model.num_gaussians < max_gaussians
    )
    if densify_due and not stretch.allow_densify:
        record.skipped.append("densify")
    elif densify_due:
        if protect is not None:
            # Follow the protected rows through clone/split (both keep their parent's buffers).
            model.register_gaussian_buffer("_protect", protect.float().unsqueeze(1))
        record.cloned, record.split = model.densify(grad_threshold, cameras_extent)
        record.densify_ran = True
        if protect is not None:
            protect = model.pop_gaussian_buffer("_protect").squeeze(1) > 0.5
    prune_due = (
        iteration > opt.pruning_from_iter
        and iteration % opt.pruning_interval == 0
        and model.num_gaussians > prune_min_gaussians
    )
    if prune_due and not stretch.allow_densify:
        record.skipped.append("prune")
    elif prune_due:
        record.pruned = model.prune(opacity_threshold, cameras_extent, size_threshold, protect=protect)
        record.prune_ran = True
    if iteration % opt.opacity_reset_interval == 0 and not stretch.allow_reset:
        record.skipped.append("opacity_reset")
    elif iteration % opt.opacity_reset_interval == 0:
        model.reset_opacity()
        record.opacity_reset = True
    record.num_gaussians = model.num_gaussians
    return record
