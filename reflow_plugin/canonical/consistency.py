"""Multi-view depth consistency of the fused static cloud (ours; the paper leaves fusion open).

Each frame's aligned depth is only as good as its depth source: monocular disparity fitted per
frame keeps a low-frequency error of its own, so two frames put the same wall at two depths, and
fusing every frame's points stacks those layers (floaters in front of the surface that the
training views then have to carve away). Every static grid point X of frame n is therefore tested
against every other frame m's aligned depth, at the 2x2 grid cells around X's projection in m
(z = X's depth in m, z_1..z_4 m's depths there):

    supports     min(z_k) (1 - tol) <= z <= max(z_k) (1 + tol)     (m sees the same surface)
    contradicts  z < min(z_k) (1 - tol)                             (X floats in front of what m
                                                                     sees: m looks through it)
    no evidence  z beyond (occluded in m), outside m's view, on m's motion mask, no depth there

and X is dropped when more frames contradict it than support it. Points no other frame sees keep
their place (no evidence against them), so a region one frame alone covers is not emptied. With
exact depth nothing contradicts, nothing is dropped.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .geometry import to_camera


@dataclass
class FrameDepth:
    """One frame's aligned depth on the provider's grid."""

    depth: np.ndarray  # [h, w] metric z-depth, NaN where unusable
    K: np.ndarray  # [3, 3]
    viewmat: np.ndarray  # [4, 4] world -> camera
    moving: np.ndarray | None  # [h, w] bool motion mask on the grid (no evidence there), or None


def votes(points: np.ndarray, frames: Sequence[FrameDepth], rows: np.ndarray, cols: np.ndarray,
          tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(support [P] int, contradiction [P] int) of world points [P, 3] over `frames` (see the module
    docstring); the grid's pixel (rows[i], cols[j]) is centred at (cols[j] + 0.5, rows[i] + 0.5)."""
    support = np.zeros(len(points), np.int32)
    against = np.zeros(len(points), np.int32)
    if not len(points):
        return support, against
    start, stride = int(cols[0]), int(cols[1] - cols[0]) if len(cols) > 1 else 1
    h, w = len(rows), len(cols)
    for frame in frames:
        cam = to_camera(points, frame.viewmat)
        z = cam[:, 2]
        front = z > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            x = frame.K[0, 0] * cam[:, 0] / z + frame.K[0, 2] - 0.5  # pixel column coordinate
            y = frame.K[1, 1] * cam[:, 1] / z + frame.K[1, 2] - 0.5
        gx, gy = (x - start) / stride, (y - start) / stride
        inside = front & np.isfinite(gx) & np.isfinite(gy) & (gx >= 0) & (gy >= 0) & (gx <= w - 1) & (gy <= h - 1)
        if not inside.any():
            continue
        idx = np.flatnonzero(inside)
        j0 = np.clip(np.floor(gx[idx]).astype(np.int64), 0, max(w - 2, 0))
        i0 = np.clip(np.floor(gy[idx]).astype(np.int64), 0, max(h - 2, 0))
        cells = [(i0 + di).clip(max=h - 1) * w + (j0 + dj).clip(max=w - 1) for di in (0, 1) for dj in (0, 1)]
        around = np.stack([frame.depth.reshape(-1)[c] for c in cells], 1)  # [Q, 4]
        if frame.moving is not None:
            moving = np.stack([frame.moving.reshape(-1)[c] for c in cells], 1).any(1)
        else:
            moving = np.zeros(len(idx), bool)
        known = np.isfinite(around).any(1) & ~moving
        filled = np.where(known[:, None], around, 1.0)  # 1.0 keeps nanmin quiet on rows that cast no vote
        low, high = np.nanmin(filled, 1), np.nanmax(filled, 1)
        zq = z[idx]
        agrees = known & (zq >= low * (1 - tol)) & (zq <= high * (1 + tol))
        floats = known & (zq < low * (1 - tol))
        support[idx[agrees]] += 1
        against[idx[floats]] += 1
    return support, against


def consistent(points: np.ndarray, own: int, frames: Sequence[FrameDepth], rows: np.ndarray, cols: np.ndarray,
               tol: float) -> np.ndarray:
    """[P] bool: frame `own`'s world points [P, 3] that no more frames contradict than support
    (every frame but `own` votes)."""
    others = [f for k, f in enumerate(frames) if k != own]
    support, against = votes(points, others, rows, cols, tol)
    return against <= support
