"""Static / dynamic split of the aligned frames (paper 3.2.1 "Static-Dynamic Disentanglement").

    static = static_cloud(provider, states, masks, voxel, consistency=0.05)  # fused, outside the masks
    dynamic, k = dynamic_cloud(provider, states, masks, max_points)   # reference frame k's masked pixels

Static: every frame's grid pixels outside its motion mask, with positive confidence and depth,
back-projected with the aligned depth (FrameState.metric_depth) and camera, then voxel-downsampled
(mean position and colour per voxel of side `voxel` x the median depth; 0 = no downsampling),
the voxel grown until at most `max_points` remain (monocular depth noise thickens the surfaces).
With `consistency` > 0 each frame's points are first tested against the other frames' aligned depth
(consistency.py: a point more frames look through than agree with is dropped).
Dynamic: the reference frame (largest mask coverage x colour diversity, seeding.reference_frame)
back-projected at full resolution inside its mask. Without masks every point is static.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from baselines.data import PointCloud

from ..seeding import reference_frame, seed_dynamic_points
from .alignment import FrameState
from .consistency import FrameDepth, consistent
from .geometry import backproject, to_world
from .providers import PointmapProvider

MIN_CONFIDENCE = 0.5  # static points: pixels whose provider confidence is above this (flow: fb error ~1 px)


def _empty() -> PointCloud:
    return PointCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))


def aligned_depth(provider: PointmapProvider, n: int, state: FrameState, full: bool = False,
                  min_confidence: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(metric depth [h, w] with NaN where unusable, valid [h, w] bool) of frame n: confidence above
    `min_confidence`, finite positive depth."""
    z, conf = state.metric_depth(provider, n, full)
    valid = np.isfinite(z) & (z > 0) & (np.nan_to_num(np.asarray(conf, np.float64)) > min_confidence)
    return np.where(valid, z, np.nan), valid


def voxel_downsample(points: np.ndarray, colours: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean point [V, 3] and colour [V, 3] per occupied voxel of side `voxel` (> 0)."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 6))
    np.add.at(sums, inverse, np.concatenate([points, colours], 1))
    means = sums / counts[:, None]
    return means[:, :3], means[:, 3:]


def static_cloud(provider: PointmapProvider, states: Mapping[int, FrameState],
                 masks: Sequence[np.ndarray] | None, voxel: float, max_points: int = 0,
                 consistency: float = 0.0, report: dict | None = None) -> PointCloud:
    """Fused static points of every frame in `states` (see the module docstring); with `max_points`
    the voxel grows by x1.25 steps until at most that many remain; with `consistency` (relative depth
    tolerance, 0 = off) points the other frames contradict are dropped first. `report` (optional)
    receives the points before / after that test."""
    rows, cols = provider.grid()
    order = sorted(states)
    depths = {n: aligned_depth(provider, n, states[n], min_confidence=MIN_CONFIDENCE) for n in order}
    grid_masks = {n: None if masks is None else masks[n][np.ix_(rows, cols)] for n in order}
    frames = [FrameDepth(depths[n][0], provider.K[n], states[n].viewmat, grid_masks[n]) for n in order]
    points, colours, before = [], [], 0
    for k, n in enumerate(order):
        z, valid = depths[n]
        if grid_masks[n] is not None:
            valid = valid & ~grid_masks[n]
        cam = backproject(np.nan_to_num(z), provider.K[n], rows, cols)
        world, colour = to_world(cam[valid], states[n].viewmat), provider.colours(n)[valid]
        before += len(world)
        if consistency > 0 and len(order) > 1:
            keep = consistent(world, k, frames, rows, cols, consistency)
            world, colour = world[keep], colour[keep]
        points.append(world)
        colours.append(colour)
    if report is not None:
        report.update(tolerance=consistency, points=before, kept=int(sum(len(p) for p in points)))
    if not points or not sum(len(p) for p in points):
        return _empty()
    P, C = np.concatenate(points), np.concatenate(colours).astype(np.float64)
    if voxel > 0:
        all_depths = np.concatenate([aligned_depth(provider, n, states[n])[0].reshape(-1) for n in order])
        side = voxel * float(np.nanmedian(all_depths))
        fused = voxel_downsample(P, C, side)
        while max_points > 0 and len(fused[0]) > max_points:
            side *= 1.25
            fused = voxel_downsample(P, C, side)
        P, C = fused
    return PointCloud(P, np.clip(C, 0, 1))


def dynamic_cloud(provider: PointmapProvider, states: Mapping[int, FrameState],
                  masks: Sequence[np.ndarray] | None, max_points: int, seed: int = 0) -> tuple[PointCloud, int | None]:
    """(points of the reference frame inside its mask, reference index or None without masks)."""
    if masks is None:
        return _empty(), None
    frames = sorted(states)
    k = reference_frame([provider.cameras[n] for n in frames], [masks[n] for n in frames])
    if k is None:
        return _empty(), None
    n = frames[k]
    z, _ = aligned_depth(provider, n, states[n], full=True)
    camera = provider.cameras[n]
    state_cam = type(camera)(**{**camera.__dict__, "viewmat": states[n].viewmat})
    return seed_dynamic_points(state_cam, masks[n], z, max_points, seed=seed), n
