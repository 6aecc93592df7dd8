"""Frame pairs for flow matching: two TRAINING frames close in time (test frames never leak in).

    sampler = PairSampler(train_cameras, window=2, seed=0)
    i, j = sampler.sample()                          # indices into train_cameras, 1 <= |pos(i) - pos(j)| <= window
    i, j = sampler.sample(center=pos_ref, radius=r)  # both frames within r positions of a reference
    j = sampler.partner(i)                           # a partner for a frame chosen elsewhere (the host's view)

Positions are ranks in time order. With `center`/`radius` the pair lies inside the allowed span
(the schedule widens the span from the frame the dynamic points were taken from, so motion is
learned outwards from where it is known). The direction (which frame is "a") is random. The
generator is seeded and saved in training checkpoints (exact resume).
"""
from __future__ import annotations

from typing import Any, Sequence

import torch

from baselines.data import Camera


class PairError(ValueError):
    """Frame pairs cannot be formed (fewer than two training frames)."""


class PairSampler:
    """Random pairs of training frames within `window` positions of each other."""

    def __init__(self, cameras: Sequence[Camera], window: int, seed: int = 0) -> None:
        if window < 1:
            raise PairError(f"pair_window must be >= 1, got {window}")
        if len(cameras) < 2:
            raise PairError(f"flow matching trains on frame pairs, but the scene has {len(cameras)} training "
                            "frame(s); give at least two (or disable full_flow and cam_flow)")
        self.order = sorted(range(len(cameras)), key=lambda i: (cameras[i].time, cameras[i].frame_index, i))
        self.position = {index: pos for pos, index in enumerate(self.order)}
        self.window = int(window)
        self.generator = torch.Generator().manual_seed(seed)

    def _partners(self, first: int, lo: int, hi: int) -> list[int]:
        """Positions that may pair with position `first` (within the window and [lo, hi])."""
        return [p for p in range(first - self.window, first + self.window + 1) if p != first and lo <= p <= hi]

    def partner(self, index: int, lo: int = 0, hi: int | None = None) -> int | None:
        """A random partner (camera index) of camera `index`, or None when it has none in [lo, hi]."""
        hi = self.num_frames - 1 if hi is None else hi
        partners = self._partners(self.position[index], lo, hi)
        return self.order[partners[self._randint(len(partners))]] if partners else None

    @property
    def num_frames(self) -> int:
        return len(self.order)

    def _randint(self, high: int) -> int:
        return int(torch.randint(high, (1,), generator=self.generator))

    def sample(self, center: int | None = None, radius: int | None = None) -> tuple[int, int]:
        """A pair (i, j) of camera indices; see the module docstring."""
        n = self.num_frames
        lo, hi = 0, n - 1
        if center is not None and radius is not None:
            center = min(max(int(center), 0), n - 1)
            lo, hi = max(0, center - max(1, radius)), min(n - 1, center + max(1, radius))
        first = lo + self._randint(hi - lo + 1)
        partners = self._partners(first, lo, hi)
        second = partners[self._randint(len(partners))]
        if self._randint(2):
            first, second = second, first
        return self.order[first], self.order[second]

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])


def curriculum_radius(iteration: int, total: int, span: int, start: int = 1) -> int:
    """Allowed distance from the reference position at `iteration` of a `total`-long widening.

    Grows linearly from `start` to `span` (the distance to the farthest frame); `total` <= 0 or
    an iteration past it gives the full span.
    """
    if total <= 0 or iteration >= total:
        return max(span, start)
    return int(round(start + (max(span, start) - start) * iteration / total))
