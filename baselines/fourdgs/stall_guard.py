"""Stop a run that cannot learn, early, with the likely cause named.

    guard = StallGuard(iterations=200)       # for a run that starts from its initial cloud
    guard.observe(ctx)                       # after every training step; raises TrainingStalled

A run whose initial cloud lies outside the training views (wrong scale, wrong frame) renders the
background in every view: its loss never changes, and it trains for an hour at a constant PSNR
without a word (seen: 6.04 dB over a whole run, the loss constant from iteration 100 on). The
guard raises `TrainingStalled` (a ValueError: train.py prints one `error:` line and exits 2) when

- no Gaussian contributed to any pixel (alpha >= 1/255) of any rendered training view for
  `iterations` consecutive steps, at any point of the run (a healthy run always renders
  something; pruning everything, or an initial cloud outside the views, renders nothing), or
- the loss is flat early in the run: within `tolerance` (1e-4) over the first `iterations`
  steps, or, for every batch of views first drawn in those steps and drawn again later, between
  its first and its latest loss. The window stays open past `iterations` until REPEATS such
  batches were drawn again (or all of them, with fewer batches; at most WAIT x `iterations`
  steps or two passes over the training views, whichever is longer), so the test works for any
  number of views: with 250 views at batch size 1 no batch repeats within 200 steps (each pass
  draws every view once), the first repeats come from step 251 on and a frozen run stops at
  step 260; with 1000 views at step 1048 (seeded sampler). A healthy loss falls by orders of
  magnitude more than 1e-4 between a view's first draw and its next; a run whose renders never
  change gives every view the same loss again.

A loss of exactly 0 is left out of the flat-loss test (the step had nothing to fit: every pixel
weighted out, as ReFlow's coarse stage does where motion masks cover the whole frame); the
visibility test still counts the step. Steps in which every Gaussian is hidden on purpose
(ctx.hidden: ReFlow's coarse stage hides the dynamic Gaussians, all of them when every Gaussian
is labelled dynamic) are not counted at all: an empty render or a flat loss there says nothing
about the cloud, and the run recovers when the stage that shows them starts.

Neither fired on a healthy run (the synthetic suite in both priors modes, the static scene). The
message gives what the cloud looks like from the cameras (how many views see a Gaussian centre,
their median depth against the dataset's near/far bounds). Per step the guard costs one max of
each rendered alpha map.
"""
from __future__ import annotations

import numpy as np
import torch

from baselines.data.cloud_check import check_cloud_against_cameras

ALPHA_VISIBLE = 1.0 / 255.0
REPEATS = 8  # batches drawn again that the flat-loss test waits for
WAIT = 5  # ... for at most this many times the guard's window


class TrainingStalled(ValueError):
    """The run cannot learn (nothing visible, or a flat loss); the message names the likely cause."""


class StallGuard:
    """Watches a run: the first `iterations` steps for a flat loss, every step for an empty render (0: never)."""

    def __init__(self, iterations: int, tolerance: float = 1e-4) -> None:
        self.iterations = int(iterations)
        self.tolerance = float(tolerance)
        self.seen = 0  # steps counted (those with some Gaussian shown)
        self.invisible_since: int | None = None  # step count at which the current empty stretch began
        self.losses: list[float] = []  # of the first `iterations` counted steps
        self.first: dict[tuple[int, ...], float] = {}  # batch -> its loss when first drawn (first window)
        self.again: dict[tuple[int, ...], float] = {}  # batch of `first` -> its latest loss since
        self.decided = False  # the flat-loss test has run
        self.zero_losses = 0  # steps whose loss was exactly 0 (not in the flat-loss test)
        self.tested = 0  # steps in the flat-loss test

    @property
    def armed(self) -> bool:
        return self.iterations > 0

    def observe(self, ctx) -> None:
        """Record one finished step (ctx.views rendered, ctx.loss computed); raise when stalled."""
        if not self.armed or _all_hidden(ctx):
            return
        self.seen += 1
        alpha = torch.stack([view.alpha.detach().max() for view in ctx.views]).max()
        if float(alpha) >= ALPHA_VISIBLE:
            self.invisible_since = None
        elif self.invisible_since is None:
            self.invisible_since = self.seen
        if self.invisible_since is not None and self.seen - self.invisible_since + 1 >= self.iterations:
            self._nothing_visible(ctx)
        if self.decided:
            return
        loss = float(ctx.metrics["loss"]) if "loss" in ctx.metrics else float(ctx.loss.detach())
        if loss == 0.0:  # every pixel weighted out (a plugin's coarse stage on masks covering the frame)
            self.zero_losses += 1
            return
        self.tested += 1
        key = tuple(sorted(c.uid for c in ctx.batch))
        if self.tested <= self.iterations:
            self.losses.append(loss)
        if key in self.first:
            self.again[key] = loss
        elif self.tested <= self.iterations:
            self.first[key] = loss
        enough = len(self.again) >= min(REPEATS, len(self.first))
        if self.tested >= self.iterations and (enough or self.tested >= self._deadline(ctx)):
            self.decided = True
            if self._flat():
                raise TrainingStalled(
                    f"training cannot learn: the loss stayed flat to {self.tolerance:g} over the first "
                    f"{self.tested} iterations ({min(self.losses):.6g} to {max(self.losses):.6g} over the first "
                    f"{len(self.losses)}; {len(self.again)} batches of views drawn again gave their first loss "
                    f"again); the Gaussians do not change the renders ({describe_cloud(ctx)}). Likely an "
                    f"initial cloud outside the views or at the wrong scale")

    def _deadline(self, ctx) -> int:
        """Steps the flat-loss test waits at most for batches drawn again: WAIT x the window, and
        at least two passes over the training views (each view drawn once per pass)."""
        views = len(getattr(ctx, "train_cameras", None) or ())
        return max(WAIT * self.iterations, 2 * -(-views // max(len(ctx.batch), 1)))

    def _flat(self) -> bool:
        if max(self.losses) - min(self.losses) <= self.tolerance:
            return True
        return bool(self.again) and all(abs(loss - self.first[key]) <= self.tolerance
                                        for key, loss in self.again.items())

    def _nothing_visible(self, ctx) -> None:
        where = (f"over the first {self.iterations} iterations; the initial cloud lies outside the views"
                 if self.invisible_since == 1 else
                 f"for {self.iterations} iterations (since step {self.invisible_since} of the run, "
                 f"{ctx.stage} iteration {ctx.iteration}): every Gaussian was pruned or became transparent")
        raise TrainingStalled(
            f"training cannot learn: no Gaussian was visible in any rendered training view {where} "
            f"({describe_cloud(ctx)}). Check the initial point cloud's source and scale against the cameras")


def _all_hidden(ctx) -> bool:
    """Whether a plugin hides every Gaussian of the model on purpose this step (ctx.hidden)."""
    hidden = getattr(ctx, "hidden", None)
    model = getattr(ctx, "model", None)
    if hidden is None or model is None:
        return False
    return hidden.numel() > 0 and hidden.numel() == model.get_xyz.shape[0] and bool(hidden.all())


def describe_cloud(ctx) -> str:
    """Where the model's Gaussian centres are as seen from the training cameras, in one clause."""
    means = ctx.model.get_xyz.detach().cpu().double().numpy()
    coverage = check_cloud_against_cameras(means, ctx.train_cameras)
    seeing = int(round(coverage.views_seeing * len(coverage.inside)))
    text = (f"cloud from {ctx.point_cloud_source}: {len(means)} Gaussians, {seeing} of {len(coverage.inside)} "
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
