"""Labels that change once: static Gaussians promoted to dynamic where the coarse fit says "moving".

    flagged = missed_motion_maps(model, cameras, masks, background, factor=4.0)   # [H, W] bool each
    promoted = promoted_gaussians(model, cameras, flagged, vote=0.5)               # [N] bool

ReFlow's labels come from the motion masks before training. An estimated mask that misses part of
an object (an umbrella turning in place: the flow-vs-camera test finds a third of it) leaves that
part static, and a static Gaussian cannot follow it. The coarse stage fits the static scene alone
(dynamic Gaussians hidden); where an unmasked pixel's colour changes over time, no static scene
fits it, so its residual stays far above the view's typical residual. Such pixels (residual above
`factor` x the view's median residual and above `floor`, outside the mask, opened by one pixel so
isolated texture errors drop out) are flagged per training view, and a static Gaussian whose
centre lies in flagged pixels in at least `vote` of the views that see it becomes dynamic. Run
once, at the start of the fine stage, on estimated masks only (a dataset's masks are trusted).
"""
from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
import torch

from baselines.data import Camera
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.renderer import render

from .labels import vote_labels


@torch.no_grad()
def missed_motion_maps(model: GaussianModel, cameras: Sequence[Camera], masks: Sequence[np.ndarray],
                       background: torch.Tensor, factor: float, floor: float = 0.05,
                       backend: str = "auto") -> list[np.ndarray]:
    """Per camera [H, W] bool: unmasked pixels the current (static) model cannot explain.

    The model is rendered as the coarse stage sees it (no deformation). Residual = mean absolute
    RGB error; flagged where it exceeds max(floor, factor x the view's median residual), outside
    `masks[k]`, after a 3x3 opening.
    """
    kernel = np.ones((3, 3), np.uint8)
    flagged = []
    for cam, mask in zip(cameras, masks):
        image = render(model, cam, "coarse", background, backend).image.clamp(0, 1)
        residual = (image - cam.image).abs().mean(-1).cpu().numpy()
        limit = max(floor, factor * float(np.median(residual)))
        hit = ((residual > limit) & ~mask).astype(np.uint8)
        flagged.append(cv2.morphologyEx(hit, cv2.MORPH_OPEN, kernel) > 0)
    return flagged


def promoted_gaussians(model: GaussianModel, cameras: Sequence[Camera], flagged: Sequence[np.ndarray],
                       vote: float = 0.5) -> np.ndarray:
    """[N] bool: static Gaussians whose centre is flagged in >= `vote` of the views that see it."""
    means = model.get_xyz.detach().cpu().double().numpy()
    static = ~model.deformation_table.cpu().numpy()
    hits = vote_labels(means, cameras, flagged, None, vote)
    return hits & static
