"""An MP4 of 2D tracks drawn over rendered views (the paper's trajectory figure, as a video).

    write_track_video(model, tracks, cameras, background, path, trail=0.3, max_tracks=400)

One frame per camera, in time order: the model rendered at the camera's time, and over it the
trails of the tracks that are visible then and not hidden behind the rendered surface (camera
depth within 10% of the rendered depth at their pixel): each trail is the track's centres at the
exported times in [t - trail, t], projected into that camera and joined, in one colour per track
(hue by the track's starting position, so neighbouring tracks share a colour), with a dot at the
current time. Tracks that barely move over the export (3D path shorter than `min_motion` x the
tracks' bounding-box diagonal) are not drawn; of the others at most `max_tracks` are drawn, the
same subset in every frame (a seeded permutation).
"""
from __future__ import annotations

import colorsys
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from baselines.fourdgs.evaluate import to_uint8, write_video
from baselines.fourdgs.renderer import render

from .tracks import Tracks, project_points

if TYPE_CHECKING:
    from baselines.data import Camera
    from baselines.fourdgs.gaussian_model import GaussianModel

OCCLUSION_TOLERANCE = 0.10  # relative camera depth beyond the rendered surface that still counts as on it


def track_colors(tracks: Tracks) -> np.ndarray:
    """[N, 3] uint8 BGR: hue from the track's first position along the tracks' main horizontal spread."""
    start = tracks.positions[0]
    axis = int(np.argmax(start.std(0))) if len(start) else 0
    lo, hi = (float(start[:, axis].min()), float(start[:, axis].max())) if len(start) else (0.0, 1.0)
    hue = (start[:, axis] - lo) / max(hi - lo, 1e-9) * 0.8
    rgb = np.array([colorsys.hsv_to_rgb(float(h), 0.9, 1.0) for h in hue]).reshape(-1, 3)
    return (rgb[:, ::-1] * 255 + 0.5).astype(np.uint8)


def moving_tracks(tracks: Tracks, min_motion: float) -> np.ndarray:
    """[N] bool: 3D path length over the exported times >= min_motion x the bounding-box diagonal."""
    if tracks.positions.shape[0] < 2 or tracks.num_tracks == 0:
        return np.zeros(tracks.num_tracks, bool)
    steps = np.linalg.norm(np.diff(tracks.positions, axis=0), axis=-1).sum(0)
    flat = tracks.positions.reshape(-1, 3)
    diagonal = float(np.linalg.norm(flat.max(0) - flat.min(0)))
    return steps >= min_motion * diagonal


def draw_tracks(image: np.ndarray, depth: np.ndarray, tracks: Tracks, K: np.ndarray, viewmat: np.ndarray,
                time: float, drawn: np.ndarray, colors: np.ndarray, trail: float) -> np.ndarray:
    """Trails of the `drawn` tracks ([N] bool) over `image` ([H, W, 3] uint8 BGR, rendered at
    `time` by the camera (K [3, 3] for that image size, viewmat [4, 4]) with expected depth
    `depth` [H, W]); returns a new image. `time` must be one of the tracks' times."""
    out = image.copy()
    now = tracks.at_time(time)
    xy_now, z_now = project_points(tracks.positions[now], K, viewmat)
    h, w = depth.shape
    shown = drawn & tracks.visible[now] & (z_now > 0.01) & np.isfinite(xy_now).all(1)
    shown &= (xy_now[:, 0] >= 0) & (xy_now[:, 0] < w) & (xy_now[:, 1] >= 0) & (xy_now[:, 1] < h)
    rows = np.flatnonzero(shown)
    px = np.clip(xy_now[rows].astype(np.int64), 0, [w - 1, h - 1])
    rows = rows[z_now[rows] <= depth[px[:, 1], px[:, 0]] * (1.0 + OCCLUSION_TOLERANCE)]
    window = [k for k, t in enumerate(tracks.times) if time - trail - 1e-6 <= t <= tracks.times[now] + 1e-6]
    points = np.stack([project_points(tracks.positions[k][rows], K, viewmat)[0] for k in window])  # [L, M, 2]
    seen = tracks.visible[window][:, rows]
    scale = 16  # sub-pixel line positions (cv2 `shift`)
    for m, track in enumerate(rows):
        path = points[:, m][seen[:, m] & np.isfinite(points[:, m]).all(1)]
        colour = tuple(int(c) for c in colors[track])
        if len(path) >= 2:
            cv2.polylines(out, [np.round(path * scale).astype(np.int32)], False, colour, 1, cv2.LINE_AA, shift=4)
        centre = tuple(int(v) for v in np.round(points[-1, m] * scale))
        cv2.circle(out, centre, 1 * scale, colour, -1, cv2.LINE_AA, shift=4)
    return out


@torch.no_grad()
def write_track_video(model: GaussianModel, tracks: Tracks, cameras: Sequence[Camera], background: Tensor,
                      path: str | Path, trail: float = 0.3, max_tracks: int = 400, min_motion: float = 0.005,
                      upscale: int = 4, fps: int = 5, backend: str = "auto", seed: int = 0) -> Path:
    """Render each camera, draw the tracks over it (module docstring) and write the MP4.

    `upscale` enlarges the rendered frame (nearest) before drawing, so trails stay readable on
    small images. Returns the path.
    """
    if not cameras:
        raise ValueError("write_track_video: no cameras to draw the tracks over")
    order = np.random.default_rng(seed).permutation(tracks.num_tracks)
    candidates = order[moving_tracks(tracks, min_motion)[order]]
    drawn = np.zeros(tracks.num_tracks, bool)
    drawn[candidates[:max_tracks]] = True
    colors = track_colors(tracks)

    def frames():
        for camera in sorted(cameras, key=lambda c: c.time):
            view = render(model, camera, "fine", background, backend)
            image = cv2.resize(to_uint8(view.image), None, fx=upscale, fy=upscale, interpolation=cv2.INTER_NEAREST)
            depth = cv2.resize(view.depth[..., 0].cpu().numpy(), None, fx=upscale, fy=upscale,
                               interpolation=cv2.INTER_NEAREST)
            K = camera.K.cpu().numpy().copy()
            K[:2] *= upscale  # continuous pixel coordinates scale with a nearest-neighbour upscale
            yield draw_tracks(image, depth, tracks, K, camera.viewmat.cpu().numpy(), camera.time, drawn, colors, trail)

    return write_video(frames(), Path(path), fps)
