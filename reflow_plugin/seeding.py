"""Dynamic points for moving objects the initial cloud misses (paper 3.2.2 "Separate Initialization").

    k = reference_frame(cameras, masks)                   # largest mask coverage x colour diversity
    cloud = seed_dynamic_points(cameras[k], masks[k], depth, max_points)

The host's triangulated cloud drops keypoints inside motion masks on purpose (SfM assumes a
static scene), so a moving object starts with no Gaussian at all. Seeding back-projects the
reference frame's masked pixels with a depth map: the dataset's disparity aligned to metric
depth (labels.aligned_depths) when there is one; otherwise the median depth of the static points
that project next to the mask (a ring around it), scaled by 0.9 because the object occludes that
background: a rough guess that flow matching and the photometric loss then correct.

The reference frame is the one whose mask covers most pixels, weighted by the colour diversity
(mean per-channel standard deviation) of the masked pixels: the frame that shows most of the
object, and not just a flat patch of it.

Keyframes (ours, beyond the paper's single reference frame): points can be seeded from several
frames spread over the sequence, each point living in a temporal opacity window around its
frame's time (separation.py). One reference frame makes the deformation learn the whole motion
from one instant, which photometric gradients, local by nature, cannot do for an object that
crosses the view; with keyframes every point only needs the motion between two keyframes.
"""
from __future__ import annotations

import logging

import cv2
import numpy as np

from baselines.data import Camera, PointCloud

from .labels import project

log = logging.getLogger(__name__)
RING_PX = 4
BACKGROUND_FACTOR = 0.9


def reference_frame(cameras: list[Camera], masks: list[np.ndarray]) -> int | None:
    """Index of the frame with the largest (mask coverage x colour diversity); None if all masks are empty."""
    best, best_score = None, 0.0
    for k, (cam, mask) in enumerate(zip(cameras, masks)):
        count = int(mask.sum())
        if count == 0:
            continue
        colours = cam.image.detach().cpu().numpy()[mask]
        diversity = float(colours.std(axis=0).mean()) if count > 1 else 0.0
        score = count * (0.05 + diversity)
        if score > best_score:
            best, best_score = k, score
    return best


def keyframes(cameras: list[Camera], masks: list[np.ndarray], count: int, reference: int) -> list[int]:
    """Up to `count` frames to seed dynamic points from: `reference` plus frames spread evenly in time.

    Only frames whose mask is not empty qualify. Returns camera indices sorted by time.
    """
    candidates = sorted((k for k, m in enumerate(masks) if m.any()), key=lambda k: cameras[k].time)
    if count <= 1 or len(candidates) <= 1:
        return [reference]
    if len(candidates) <= count:
        return candidates
    times = np.array([cameras[k].time for k in candidates])
    chosen: list[int] = []
    for target in np.linspace(times.min(), times.max(), count):  # both ends included
        order = np.argsort(np.abs(times - target), kind="stable")
        chosen.append(next(candidates[i] for i in order if candidates[i] not in chosen))
    if reference not in chosen:  # the reference replaces the pick closest to it in time
        closest = min(range(len(chosen)), key=lambda i: abs(cameras[chosen[i]].time - cameras[reference].time))
        chosen[closest] = reference
    return sorted(chosen, key=lambda k: cameras[k].time)


def window_scale(times: list[float]) -> float:
    """Initial temporal standard deviation of keyframe seeds: 0.6 x the mean keyframe spacing
    (neighbouring windows overlap, so every time between two keyframes sees at least one)."""
    if len(times) < 2:
        return float("inf")
    return 0.6 * float(np.mean(np.diff(sorted(times))))


def ring_depth(camera: Camera, mask: np.ndarray, static_points: np.ndarray) -> float | None:
    """Median depth of the static points projecting into a ring of RING_PX pixels around `mask`."""
    if len(static_points) == 0:
        return None
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * RING_PX + 1,) * 2)
    ring = cv2.dilate(mask.astype(np.uint8), kernel).astype(bool) & ~mask
    x, y, z = project(np.asarray(static_points, np.float64), camera)
    col, row = np.floor(x).astype(int), np.floor(y).astype(int)
    seen = (z > 1e-6) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    seen[seen] &= ring[row[seen], col[seen]]
    if seen.sum() < 3:
        seen = (z > 1e-6) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
        if seen.sum() < 3:
            return None
    return float(np.median(z[seen]))


def depth_edges(depth: np.ndarray, ratio: float) -> np.ndarray:
    """[H, W] bool: pixels whose 3x3 neighbourhood spans a depth ratio above `ratio` (or has no depth).

    A monocular depth map's edges are soft: the pixels between an object and what lies behind it
    get depths in between, and back-projected they float in the gap (a halo around the object).
    """
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    highest = cv2.dilate(z, kernel)
    lowest = cv2.erode(z, kernel)
    return ~(highest <= ratio * lowest)


def snap_edges_to_nearer(depth: np.ndarray, ratio: float) -> np.ndarray:
    """[H, W] depth with the pixels on depth edges (`depth_edges`) set to the smallest valid depth
    of their 5x5 neighbourhood (unchanged elsewhere)."""
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).astype(np.float32)
    nearest = cv2.erode(z, np.ones((5, 5), np.uint8)).astype(np.float64)
    edges = depth_edges(depth, ratio) & np.isfinite(nearest)
    return np.where(edges, nearest, depth)


def seed_dynamic_points(camera: Camera, mask: np.ndarray, depth: np.ndarray | float, max_points: int,
                        seed: int = 0, edge_ratio: float = 0.0) -> PointCloud:
    """Back-project the masked pixels of `camera` ([P, 3] world points, their colours).

    Args:
        mask: [H, W] bool. depth: [H, W] metric z-depth, or one value for every pixel.
        max_points: at most this many pixels, evenly subsampled (seeded).
        edge_ratio: > 0: pixels on depth edges (`depth_edges` at this ratio) take the NEAREST depth of
            their 5x5 neighbourhood (a moving object occludes what is behind it, so its rim belongs
            to the nearer surface; thin parts keep their pixels).
    Pixels with a non-finite or non-positive depth are skipped.
    """
    if edge_ratio > 0 and not np.isscalar(depth):
        depth = snap_edges_to_nearer(np.asarray(depth, np.float64), edge_ratio)
    rows, cols = np.nonzero(mask)
    z = np.full(len(rows), float(depth)) if np.isscalar(depth) else np.asarray(depth, np.float64)[rows, cols]
    ok = np.isfinite(z) & (z > 0)
    rows, cols, z = rows[ok], cols[ok], z[ok]
    if len(rows) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(rows), max_points, replace=False))
        rows, cols, z = rows[keep], cols[keep], z[keep]
    K = camera.K.detach().cpu().double().numpy()
    viewmat = camera.viewmat.detach().cpu().double().numpy()
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows + 0.5 - K[1, 2]) / K[1, 1] * z
    cam_points = np.stack([x, y, z], 1)
    world = (cam_points - viewmat[:3, 3]) @ viewmat[:3, :3]  # R^T (p - t)
    colours = camera.image.detach().cpu().numpy()[rows, cols]
    return PointCloud(world.astype(np.float32), np.clip(colours, 0, 1).astype(np.float32))
