"""Labels that change: static Gaussians promoted to dynamic where the fit says "moving".

    flagged = missed_motion_maps(model, cameras, masks, background, factor=4.0)   # [H, W] bool each
    promoted = promoted_gaussians(model, cameras, flagged, vote=0.5)               # [N] bool

    votes = ResidualVotes(factor=3.0)          # during the fine stage (`--relabel_every`)
    votes.accumulate(model, view, mask)        # every iteration, from the view the host rendered
    promoted = votes.promote(model, vote=0.5, min_views=5)   # every K iterations; resets the counts

ReFlow's labels come from the motion masks before training. An estimated mask that misses part of
an object (an umbrella turning in place: the flow-vs-camera test finds a third of it) leaves that
part static, and a static Gaussian cannot follow it. The coarse stage fits the static scene alone
(dynamic Gaussians hidden); where an unmasked pixel's colour changes over time, no static scene
fits it, so its residual stays far above the view's typical residual. Such pixels (residual above
`factor` x the view's median residual and above `floor`, outside the mask, opened by one pixel so
isolated texture errors drop out) are flagged per training view, and a static Gaussian whose
centre lies in flagged pixels in at least `vote` of the views that see it becomes dynamic. Run
once, at the start of the fine stage, on estimated masks only (a dataset's masks are trusted).

`ResidualVotes` asks the same question DURING the fine stage, of the model being trained (its
dynamic branch already fits what the masks found, and the static texture is fitted by then, so
what stays far above the view's typical residual is motion nobody models): every iteration, the
training view the host rendered is thresholded as above, and each static Gaussian whose projected
centre lies in the view counts one view seen and, if its centre's pixel is flagged, one hit. The
counts are per-Gaussian buffers, so clone/split/prune keep them in step. Every K iterations the
static Gaussians with at least `min_views` views and a hit share >= `vote` become dynamic, if they
lie inside the dynamic branch's box (its coordinates are not re-fitted while it trains), and the
counts restart. No extra render: it reads the host's render and projection. Both are off by
default: on the real-priors suite neither moved PSNR by more than the run-to-run spread (README,
"Labels that change once" and "Labels that change during training").
"""
from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from baselines.data import Camera
from baselines.fourdgs.hooks import ViewRender
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


def open_3x3(hit: Tensor) -> Tensor:
    """[H, W] bool -> [H, W] bool: morphological opening with a 3x3 square (isolated pixels drop out)."""
    x = hit.to(torch.float32)[None, None]
    eroded = -F.max_pool2d(-x, 3, stride=1, padding=1)
    return F.max_pool2d(eroded, 3, stride=1, padding=1)[0, 0] > 0.5


class ResidualVotes:
    """Per-Gaussian votes "this static Gaussian sits on motion nobody models" (module docstring).

    Args:
        factor: a pixel is flagged where its mean absolute RGB error exceeds factor x the view's
            median error (and `floor`).
        floor: the smallest residual that can be flagged.
    """

    HITS = "reflow_relabel_hits"  # [N, 1] float buffer: views whose flagged pixels hold the centre
    SEEN = "reflow_relabel_seen"  # [N, 1] float buffer: views that saw the centre

    def __init__(self, factor: float, floor: float = 0.05) -> None:
        self.factor = float(factor)
        self.floor = float(floor)

    def _counts(self, model: GaussianModel) -> tuple[Tensor, Tensor]:
        for name in (self.HITS, self.SEEN):
            if name not in model.registered_buffers:
                model.register_gaussian_buffer(name, torch.zeros(model.num_gaussians, 1, device=model.device))
        return model.registered_buffers[self.HITS], model.registered_buffers[self.SEEN]

    @torch.no_grad()
    def flagged(self, image: Tensor, target: Tensor, mask: Tensor | None) -> Tensor:
        """[H, W] bool: pixels of a render `image` [H, W, 3] far from `target` [H, W, 3], outside `mask`."""
        residual = (image.detach().clamp(0, 1) - target).abs().mean(-1)
        limit = torch.clamp_min(self.factor * residual.median(), self.floor)
        hit = residual > limit
        if mask is not None:
            hit = hit & ~mask.to(hit.device, torch.bool)
        return open_3x3(hit)

    @torch.no_grad()
    def accumulate(self, model: GaussianModel, view: ViewRender, mask: Tensor | None) -> None:
        """Count one view for every static Gaussian whose centre projects inside `view`'s image.

        `view` is a rendered batch view (image set); its projection rows are the model's rows.
        """
        if view.image is None or view.projection.means2d.shape[0] != model.num_gaussians:
            return
        hits, seen = self._counts(model)
        flagged = self.flagged(view.image, view.camera.image, mask)
        height, width = flagged.shape
        pixel = view.projection.means2d.detach().floor().long()
        x, y = pixel[:, 0], pixel[:, 1]
        counted = (view.projection.visible & ~model.deformation_table.to(pixel.device)
                   & (x >= 0) & (x < width) & (y >= 0) & (y < height))
        rows = counted.nonzero().squeeze(1)
        seen[rows] += 1.0
        hits[rows] += flagged[y[rows], x[rows]].to(hits.dtype).unsqueeze(1)

    @torch.no_grad()
    def promote(self, model: GaussianModel, vote: float, min_views: int) -> Tensor:
        """[N] bool: the static Gaussians to make dynamic now; every count restarts at zero.

        A Gaussian qualifies with >= `min_views` views counted, a hit share >= `vote`, and its
        centre inside the deformation module's box (where it has one: `get_aabb`).
        """
        hits, seen = self._counts(model)
        table = model.deformation_table.to(hits.device)
        share = hits[:, 0] / seen[:, 0].clamp_min(1.0)
        chosen = ~table & (seen[:, 0] >= min_views) & (share >= vote)
        box = getattr(model.deformation, "get_aabb", None)
        if box is not None:
            high, low = box
            means = model.get_xyz.detach().to(high.device)
            chosen &= ((means >= low) & (means <= high)).all(1).to(chosen.device)
        model.set_gaussian_buffer(self.HITS, torch.zeros_like(hits))
        model.set_gaussian_buffer(self.SEEN, torch.zeros_like(seen))
        return chosen
