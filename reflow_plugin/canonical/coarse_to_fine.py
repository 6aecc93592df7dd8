"""Coarse-to-fine alignment (paper 3.2.1, appendix A.1): keyframe graph first, then each clip.

    states, report = align_sequence(provider, frames, weights, mode="coarse_to_fine", clip_len=25, window=4)

Frames (camera indices sorted by time) are cut into clips of `clip_len`; the first frame of each
clip is its keyframe. The keyframes are aligned over their complete pair graph; then each clip is
aligned over its pairs at most `window` frames apart plus every frame's pair with its keyframe,
the keyframe held fixed (the anchor). That is the free-pose case; with the dataset's cameras
held fixed (a run) the cameras already tie the clips together, so the keyframe graph is skipped
and each keyframe is aligned with its clip (`hold_keyframes` forces the paper's anchoring).
With K = N / clip_len keyframes the work is at most O(K^2 + N (window + 1)): linear in N for a
fixed clip length, against O(N^2) for mode="full" (every pair at once).

A clip shorter than the window just has fewer pairs; a one-frame clip is its keyframe (aligned
in the keyframe graph, or else paired with the previous frame, held); with a single keyframe
(N <= clip_len) the clip is aligned on its own.
"""
from __future__ import annotations

import itertools
import time
from typing import Mapping, Sequence

import numpy as np

from .alignment import FrameState, align_frames
from .providers import PointmapProvider

MODES = ("coarse_to_fine", "full")


def clips(frames: Sequence[int], clip_len: int) -> list[list[int]]:
    """Consecutive non-overlapping clips of at most `clip_len` frames."""
    return [list(frames[k:k + clip_len]) for k in range(0, len(frames), clip_len)]


def clip_edges(clip: Sequence[int], window: int) -> list[tuple[int, int]]:
    """Pairs at most `window` positions apart inside the clip, plus (keyframe, frame) pairs."""
    edges = {(clip[a], clip[b]) for a in range(len(clip)) for b in range(a + 1, min(len(clip), a + window + 1))}
    edges |= {(clip[0], f) for f in clip[1:]}
    return sorted(edges)


def align_sequence(provider: PointmapProvider, frames: Sequence[int], weights: Mapping[int, np.ndarray],
                   mode: str = "coarse_to_fine", clip_len: int = 25, window: int = 4, free_poses: bool = False,
                   iterations: int = 300, progress: bool = False, device="cpu",
                   hold_keyframes: bool | None = None) -> tuple[dict[int, FrameState], dict]:
    """States of every frame and a report {mode, keyframes, clips, edges, residuals, seconds}.

    hold_keyframes: hold each clip's keyframe at its keyframe-graph state (None: with free poses
    only; with the dataset's cameras those already tie the clips together, and a keyframe pair far
    apart in time is the least reliable prediction: measured with the flow provider on the
    embedded scene, held keyframes put two clips' scales at 0.83 and 1.07).
    """
    if mode not in MODES:
        raise ValueError(f"canonical: unknown alignment mode {mode!r} ({', '.join(MODES)})")
    if len(frames) < 2:
        raise ValueError(f"canonical space: alignment needs at least 2 frames, got {len(frames)}")
    if mode == "coarse_to_fine" and clip_len < 2:
        raise ValueError(f"canonical_clip_len must be at least 2 (a clip pairs its frames), got {clip_len}")
    start = time.perf_counter()
    common = dict(free_poses=free_poses, iterations=iterations, progress=progress, device=device)
    if mode == "full":
        states, stage = align_frames(provider, frames, list(itertools.combinations(frames, 2)), weights,
                                     desc="align (full graph)", **common)
        return states, {"mode": mode, "stages": [stage], "edges": stage["edges"],
                        "residual": stage["residual"], "seconds": time.perf_counter() - start}
    parts = clips(frames, clip_len)
    keys = [c[0] for c in parts]
    held = hold_keyframes if hold_keyframes is not None else free_poses
    stages, states = [], {}
    if held and len(keys) >= 2:
        states, stage = align_frames(provider, keys, list(itertools.combinations(keys, 2)), weights,
                                     desc="align keyframes", **common)
        stages.append(dict(stage, stage="keyframes"))
    for k, clip in enumerate(parts):
        if len(clip) == 1 and clip[0] in states:
            continue
        if len(clip) == 1:  # a lone last frame: paired with the previous frame, which is held
            clip = [parts[k - 1][-1], clip[0]]
            anchor = {clip[0]: states[clip[0]]}
            clip_states, stage = align_frames(provider, clip, [tuple(clip)], weights, fixed=anchor,
                                              desc=f"align clip {k + 1}/{len(parts)}", **common)
            states.update(clip_states)
            stages.append(dict(stage, stage=f"clip {k}"))
            continue
        anchor = {clip[0]: states[clip[0]]} if clip[0] in states and states[clip[0]].determined else {}
        clip_states, stage = align_frames(provider, clip, clip_edges(clip, window), weights, fixed=anchor,
                                          desc=f"align clip {k + 1}/{len(parts)}", **common)
        states.update(clip_states)
        stages.append(dict(stage, stage=f"clip {k}"))
    residuals = [s["residual"] for s in stages if s["residual"] is not None]
    return states, {"mode": mode, "keyframes": [provider.cameras[k].image_name for k in keys], "keyframes_held": held,
                    "clips": len(parts), "stages": stages, "edges": sum(s["edges"] for s in stages),
                    "residual": float(np.mean(residuals)) if residuals else None,
                    "seconds": time.perf_counter() - start}


def unaligned(provider: PointmapProvider, frames: Sequence[int]) -> tuple[dict[int, FrameState], dict]:
    """The paper's "w/o align" ablation: raw provider depths with the dataset's cameras."""
    return ({n: FrameState(1.0, 0.0, provider.viewmats[n]) for n in frames},
            {"mode": "none (w/o align)", "edges": 0, "residual": None, "seconds": 0.0})
