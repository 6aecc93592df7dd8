"""Exact ground-truth optical flow and occlusion between two frames.

For each pixel centre q of frame a: take the surface point it sees (object k, unit-shape
coordinates p), move it with object k's motion to frame b's time (X_b = M_k(t_b) p), project it
with frame b's camera: flow = proj_b(X_b) - q. The point counts as occluded in b when it is behind
camera b, projects outside b's image, belongs to an object absent at t_b, or is not the first
surface along b's ray through its projection (object id or depth differ), which is the exact
form of "compare with frame b's depth" (no depth-map sampling at silhouettes).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .raycast import FrameCamera, Hits, cast
from .scene import Placement

# Relative depth agreement that counts as "the same surface point" (geometry is float64, so the
# two paths to the depth differ by rounding only).
_DEPTH_RTOL = 1e-6
_NEAR = 1e-6


def scene_flow(hits_a: Hits, cam_a: FrameCamera, cam_b: FrameCamera,
               placements_b: Sequence[Placement]) -> tuple[np.ndarray, np.ndarray]:
    """Flow from frame a to frame b at a's pixel centres.

    Args:
        hits_a: centre-ray hits of frame a, row-major [H*W].
        cam_a, cam_b: the two frames' cameras (same image size).
        placements_b: every renderable object at frame b's time (present or not).
    Returns:
        flow [H,W,2] float32 (dx, dy) in pixels (0 where the point is behind camera b), and
        occluded [H,W] bool (occluded at b, behind camera b, outside b's image, or object absent).
    """
    h, w = cam_a.height, cam_a.width
    centres = cam_a.pixel_grid()
    by_index = {p.index: p for p in placements_b}
    world = np.zeros((h * w, 3))
    alive = np.zeros(h * w, dtype=bool)
    for k in np.unique(hits_a.index[hits_a.index >= 0]):
        rows = np.flatnonzero(hits_a.index == k)
        place = by_index[int(k)]
        world[rows] = hits_a.local[rows] @ place.to_world[:3, :3].T + place.to_world[:3, 3]
        alive[rows] = place.present
    view = cam_b.viewmat
    cam_points = world @ view[:3, :3].T + view[:3, 3]
    z = cam_points[:, 2]
    in_front = z > _NEAR
    projected = np.zeros((h * w, 2))
    pix = cam_points[in_front] @ cam_b.K.T
    projected[in_front] = pix[:, :2] / pix[:, 2:3]
    flow = np.where(in_front[:, None], projected - centres, 0.0)
    inside = (in_front & (projected[:, 0] >= 0.0) & (projected[:, 0] < cam_b.width)
              & (projected[:, 1] >= 0.0) & (projected[:, 1] < cam_b.height))
    candidates = np.flatnonzero(inside & alive & (hits_a.index >= 0))
    visible = np.zeros(h * w, dtype=bool)
    if len(candidates):
        seen = cast(placements_b, cam_b.center, cam_b.directions(projected[candidates]))
        same = ((seen.index == hits_a.index[candidates])
                & (np.abs(seen.depth - z[candidates]) <= _DEPTH_RTOL * z[candidates]))
        visible[candidates[same]] = True
    return flow.reshape(h, w, 2).astype(np.float32), ~visible.reshape(h, w)
