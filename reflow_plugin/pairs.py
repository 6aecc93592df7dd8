"""Frame pairs for flow matching: two TRAINING frames close in time (test frames never leak in).

    sampler = PairSampler(train_cameras, window=2, seed=0)
    i, j = sampler.sample()                          # indices into train_cameras, 1 <= |pos(i) - pos(j)| <= window
    i, j = sampler.sample(center=pos_ref, radius=r)  # both frames within r positions of a reference
    j = sampler.partner(i)                           # a partner for a frame chosen elsewhere (the host's view)

Positions are ranks in time order. With `center`/`radius` the pair lies inside the allowed span
(the schedule widens the span from the frame the dynamic points were taken from, so motion is
learned outwards from where it is known). The direction (which frame is "a") is random. The
generator is seeded and saved in training checkpoints (exact resume).

`sequences` (camera indices in the orders frames are paired in; default: one, all frames in time
order) lets a wide rig read monocularly pair each frame with frames of ITS OWN rig camera
(`labels.pairing_sequences`): "within `window`" then counts along the frame's first sequence with
another frame, so a partner is the same camera's next occurrence, not the time neighbour seen from
a camera 26-68 degrees away, whose warp is a wide-baseline match full of occlusions. A frame whose
sequence has no other frame in the allowed span is drawn again among those that have one; when
none has, pairs fall back to time order.
"""
from __future__ import annotations

from typing import Any, Sequence

import torch

from baselines.data import Camera


class PairError(ValueError):
    """Frame pairs cannot be formed (fewer than two training frames)."""


class PairSampler:
    """Random pairs of training frames within `window` positions of each other."""

    def __init__(self, cameras: Sequence[Camera], window: int, seed: int = 0,
                 sequences: Sequence[Sequence[int]] | None = None) -> None:
        if window < 1:
            raise PairError(f"pair_window must be >= 1, got {window}")
        if len(cameras) < 2:
            raise PairError(f"flow matching trains on frame pairs, but the scene has {len(cameras)} training "
                            "frame(s); give at least two (or disable full_flow and cam_flow)")
        self.order = sorted(range(len(cameras)), key=lambda i: (cameras[i].time, cameras[i].frame_index, i))
        self.position = {index: pos for pos, index in enumerate(self.order)}
        self.window = int(window)
        self.generator = torch.Generator().manual_seed(seed)
        # per position: (its sequence as positions, its place there); None = time order itself
        self._home: list[tuple[list[int], int]] | None = None
        if sequences is not None:
            self._home = self._homes(sequences, len(cameras))

    def _homes(self, sequences: Sequence[Sequence[int]], count: int) -> list[tuple[list[int], int]]:
        """Each position's pairing sequence: the first given sequence holding it with another frame,
        else time order."""
        home: list[tuple[list[int], int] | None] = [None] * count
        for sequence in sequences:
            if any(not 0 <= int(i) < count for i in sequence) or len(set(sequence)) != len(sequence):
                raise PairError(f"pair sequences must hold distinct camera indices in [0, {count}), got {list(sequence)}")
            positions = [self.position[int(i)] for i in sequence]
            if len(positions) < 2:
                continue
            for place, pos in enumerate(positions):
                if home[pos] is None:
                    home[pos] = (positions, place)
        time_order = list(range(count))
        return [h if h is not None else (time_order, pos) for pos, h in enumerate(home)]

    def _partners(self, first: int, lo: int, hi: int) -> list[int]:
        """Positions that may pair with position `first` (within the window of its sequence and [lo, hi])."""
        if self._home is None:
            return self._time_partners(first, lo, hi)
        sequence, place = self._home[first]
        near = sequence[max(0, place - self.window):place + self.window + 1]
        return [p for p in near if p != first and lo <= p <= hi]

    def _time_partners(self, first: int, lo: int, hi: int) -> list[int]:
        """Positions within the window of `first` in time order and in [lo, hi]."""
        return [p for p in range(first - self.window, first + self.window + 1) if p != first and lo <= p <= hi]

    def partner(self, index: int, lo: int = 0, hi: int | None = None) -> int | None:
        """A random partner (camera index) of camera `index`, or None when it has none in [lo, hi]."""
        hi = self.num_frames - 1 if hi is None else hi
        first = self.position[index]
        partners = self._partners(first, lo, hi) or self._time_partners(first, lo, hi)
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
        if not partners:  # only with sequences: none of this frame's sequence lies in the span
            firsts = [p for p in range(lo, hi + 1) if self._partners(p, lo, hi)]
            if firsts:
                first = firsts[self._randint(len(firsts))]
                partners = self._partners(first, lo, hi)
            else:
                partners = self._time_partners(first, lo, hi)
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
