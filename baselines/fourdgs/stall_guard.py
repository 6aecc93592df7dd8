"""Stop a run that cannot learn, early, with the likely cause named.

    guard = StallGuard(iterations=200)       # armed for a run that starts from its initial cloud
    guard.observe(ctx)                       # after every training step; raises TrainingStalled

A run whose initial cloud lies outside the training views (wrong scale, wrong frame) renders the
background in every view: its loss never changes, and it trains for an hour at a constant PSNR
without a word (seen: 6.04 dB over a whole run). Over its first `iterations` steps the guard
records whether any rendered view had a pixel with alpha >= 1/255 and the loss of every step.
At the end of that window it raises `TrainingStalled` (a ValueError: train.py prints one
`error:` line and exits 2) when

- no Gaussian contributed to any pixel of any rendered training view, or
- the loss is flat: within `tolerance` (1e-4) over the whole window, or within it between the
  first and the last time each batch of views was drawn (every batch drawn twice or more).

Then it disarms: later iterations cost nothing. A healthy run's loss falls by orders of magnitude
more than 1e-4 within a few dozen steps, so neither test fires on one (checked on the synthetic
suite and a static scene). The message gives what the cloud looks like from the cameras (how many
views see a Gaussian centre, their median depth against the dataset's near/far bounds).
"""
from __future__ import annotations

import numpy as np
import torch

from baselines.data.cloud_check import check_cloud_against_cameras

ALPHA_VISIBLE = 1.0 / 255.0


class TrainingStalled(ValueError):
    """The run cannot learn (nothing visible, or a flat loss); the message names the likely cause."""


class StallGuard:
    """Watches the first `iterations` training steps of a run (0: never)."""

    def __init__(self, iterations: int, tolerance: float = 1e-4) -> None:
        self.iterations = int(iterations)
        self.tolerance = float(tolerance)
        self.seen = 0
        self.visible_steps = 0
        self.losses: list[float] = []
        self.by_batch: dict[tuple[int, ...], list[float]] = {}

    @property
    def armed(self) -> bool:
        return 0 < self.iterations and self.seen < self.iterations

    def observe(self, ctx) -> None:
        """Record one finished step (ctx.views rendered, ctx.loss computed); raise at the window's end."""
        if not self.armed:
            return
        self.seen += 1
        alpha = torch.stack([view.alpha.detach().max() for view in ctx.views]).max()
        self.visible_steps += int(float(alpha) >= ALPHA_VISIBLE)
        loss = float(ctx.metrics.get("loss", float(ctx.loss.detach())))
        self.losses.append(loss)
        self.by_batch.setdefault(tuple(sorted(c.uid for c in ctx.batch)), []).append(loss)
        if self.seen == self.iterations:
            self._verdict(ctx)

    def _flat(self) -> bool:
        if max(self.losses) - min(self.losses) <= self.tolerance:
            return True
        repeated = [v for v in self.by_batch.values() if len(v) >= 2]
        return bool(repeated) and all(abs(v[-1] - v[0]) <= self.tolerance for v in repeated)

    def _verdict(self, ctx) -> None:
        if self.visible_steps == 0:
            raise TrainingStalled(
                f"training cannot learn: no Gaussian was visible in any rendered training view over the first "
                f"{self.iterations} iterations; the initial cloud lies outside the views ({describe_cloud(ctx)}). "
                f"Check the initial point cloud's source and scale against the cameras")
        if self._flat():
            raise TrainingStalled(
                f"training cannot learn: the loss stayed flat to {self.tolerance:g} over the first {self.iterations} "
                f"iterations ({min(self.losses):.6g} to {max(self.losses):.6g}); the Gaussians do not change the "
                f"renders ({describe_cloud(ctx)}). Likely an initial cloud outside the views or at the wrong scale")


def describe_cloud(ctx) -> str:
    """Where the model's Gaussian centres are as seen from the training cameras, in one clause."""
    means = ctx.model.get_xyz.detach().cpu().double().numpy()
    coverage = check_cloud_against_cameras(means, ctx.train_cameras)
    seeing = int(round(coverage.views_seeing * len(coverage.inside)))
    text = (f"initial cloud from {ctx.point_cloud_source}: {len(means)} Gaussians, {seeing} of {len(coverage.inside)} "
            f"views see a centre, {coverage.points_seen:.1%} of the centres lie inside some view")
    camera = ctx.train_cameras[0]
    viewmat = camera.viewmat.detach().cpu().double().numpy()
    z = means @ viewmat[2, :3] + viewmat[2, 3]
    if (z > 0).any():
        text += f", median depth {float(np.median(z[z > 0])):.4g} in {camera.image_name}"
    near_far = getattr(ctx.scene, "near_far", None)
    if near_far is not None:
        text += f" (dataset near/far {near_far[0]:.4g}-{near_far[1]:.4g})"
    return text


__all__ = ["StallGuard", "TrainingStalled", "describe_cloud"]
