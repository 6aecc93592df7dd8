"""3D tracks of a trained model's deformed Gaussians: centres over time, with visibility.

    tracks = compute_tracks(model, times, rows=dynamic_rows(model))
    save_tracks(path, tracks)          # npz, readable with numpy alone
    tracks = load_tracks(path)

The npz holds (T times, N tracks):
    times      [T]        float32, the times the model was deformed to
    positions  [T, N, 3]  float32 world centres (the deformed means)
    visible    [T, N]     bool: the Gaussian exists at that time (see below)
    opacity    [T, N]     float32, deformed opacity at that time (temporal windows included)
    indices    [N]        int64 row of each track in the model (point_cloud.ply order)
    colors     [N, 3]     float32 RGB of the SH DC term (3DGS's SH2RGB, clipped to [0, 1])
    dynamic    [N]        bool, the model's deformation table at those rows
and the run's cameras (V views, train and test), so the tracks can be projected without the run:
    view_frame [V] int64 frame index, view_time [V] float32, view_test [V] bool (held out),
    view_K [V, 3, 3], view_viewmat [V, 4, 4] (world-to-camera, OpenCV axes), view_size [V, 2] (W, H)

Visibility is read off what the deformation does to the opacity, so it needs no knowledge of the
plugin that trained the model: visible[t, n] when opacity[t, n] >= VISIBLE_FRACTION x the
Gaussian's stored (canonical) opacity. A keyframe copy of a moving object (ReFlow's seeds, whose
deformation multiplies the opacity by a temporal window exp(-((t - c) / s)^2 / 2)) is therefore
visible inside its window (within 1.18 s of its keyframe c) and not outside; a Gaussian whose
opacity the deformation leaves alone (4DGS's default, `no_do`) is visible at every time.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch
from torch import Tensor

from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.render.sh import SH2RGB

if TYPE_CHECKING:
    from baselines.data import Camera

VISIBLE_FRACTION = 0.5  # half the stored opacity: inside a temporal window's half-maximum
TRACK_KEYS = ("times", "positions", "visible", "opacity", "indices", "colors", "dynamic")
VIEW_KEYS = ("view_frame", "view_time", "view_test", "view_K", "view_viewmat", "view_size")


@dataclass
class Tracks:
    """T times x N tracks (the npz keys of the module docstring, as numpy arrays)."""

    times: np.ndarray
    positions: np.ndarray
    visible: np.ndarray
    opacity: np.ndarray
    indices: np.ndarray
    colors: np.ndarray
    dynamic: np.ndarray
    view_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    view_time: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    view_test: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    view_K: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3), np.float32))
    view_viewmat: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4), np.float32))
    view_size: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))

    def set_views(self, train: Sequence[Camera], test: Sequence[Camera]) -> None:
        """Record the run's cameras (train and test) in frame order."""
        cams = sorted([(c, False) for c in train] + [(c, True) for c in test], key=lambda ct: ct[0].frame_index)
        self.view_frame = np.array([c.frame_index for c, _ in cams], np.int64)
        self.view_time = np.array([c.time for c, _ in cams], np.float32)
        self.view_test = np.array([is_test for _, is_test in cams], bool)
        self.view_K = np.stack([c.K.detach().cpu().numpy() for c, _ in cams]).astype(np.float32) if cams else self.view_K
        self.view_viewmat = (np.stack([c.viewmat.detach().cpu().numpy() for c, _ in cams]).astype(np.float32)
                             if cams else self.view_viewmat)
        self.view_size = np.array([(c.width, c.height) for c, _ in cams], np.int64).reshape(-1, 2)

    @property
    def num_tracks(self) -> int:
        return int(self.positions.shape[1])

    def at_time(self, time: float, atol: float = 1e-5) -> int:
        """Index of `time` in `times` (ValueError naming the nearest one when it is not there)."""
        gaps = np.abs(self.times.astype(np.float64) - float(time))
        k = int(np.argmin(gaps))
        if gaps[k] > atol:
            raise ValueError(f"tracks have no time {time:.6g} (nearest {float(self.times[k]):.6g})")
        return k


def dynamic_rows(model: GaussianModel) -> Tensor:
    """[M] int64 rows of the Gaussians the deformation moves (the deformation table's True rows)."""
    return model.deformation_table.nonzero().squeeze(1)


@torch.no_grad()
def compute_tracks(model: GaussianModel, times: Sequence[float], rows: Tensor | None = None,
                   stage: str = "fine") -> Tracks:
    """Deform the model to each time and keep the centres (and opacities) of `rows` (all if None).

    One `model.deform` per time over the whole model (a deformation module may depend on every
    row's buffers); memory is T x N x 4 floats for the kept rows.
    """
    if len(times) == 0:
        raise ValueError("compute_tracks: no times given")
    rows = torch.arange(model.num_gaussians, device=model.device) if rows is None else rows.to(model.device)
    stored = torch.sigmoid(model._opacity.detach()[rows]).squeeze(1)
    positions, opacity = [], []
    for t in times:
        state = model.deform(float(t), stage)
        positions.append(state.means[rows].float().cpu())
        opacity.append(state.opacities[rows].float().cpu())
    opacity_t = torch.stack(opacity)
    visible = opacity_t >= VISIBLE_FRACTION * stored.float().cpu().unsqueeze(0)
    colors = SH2RGB(model._features_dc.detach()[rows, 0]).clamp(0.0, 1.0)
    return Tracks(
        times=np.asarray(times, dtype=np.float32),
        positions=torch.stack(positions).numpy(),
        visible=visible.numpy(),
        opacity=opacity_t.numpy(),
        indices=rows.cpu().numpy().astype(np.int64),
        colors=colors.float().cpu().numpy(),
        dynamic=model.deformation_table[rows].cpu().numpy(),
    )


def save_tracks(path: str | Path, tracks: Tracks) -> Path:
    """Write the npz (compressed) through a temp name renamed into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **{k: getattr(tracks, k) for k in TRACK_KEYS + VIEW_KEYS})
    tmp.replace(path)
    return path


def load_tracks(path: str | Path) -> Tracks:
    """Read an npz written by `save_tracks` (ValueError naming a missing key or a shape mismatch)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: tracks file not found")
    with np.load(path) as data:
        missing = [k for k in TRACK_KEYS if k not in data.files]
        if missing:
            raise ValueError(f"{path}: not a tracks file (missing {', '.join(missing)})")
        tracks = Tracks(**{k: data[k] for k in TRACK_KEYS + VIEW_KEYS if k in data.files})
    t, n = len(tracks.times), tracks.indices.shape[0]
    expected = {"positions": (t, n, 3), "visible": (t, n), "opacity": (t, n), "colors": (n, 3), "dynamic": (n,)}
    v = len(tracks.view_frame)
    expected.update({"view_time": (v,), "view_test": (v,), "view_K": (v, 3, 3), "view_viewmat": (v, 4, 4),
                     "view_size": (v, 2)})
    for key, shape in expected.items():
        if getattr(tracks, key).shape != shape:
            raise ValueError(f"{path}: {key} has shape {getattr(tracks, key).shape}, expected {shape}")
    return tracks


def project_points(points: np.ndarray, K: np.ndarray, viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [M, 3] -> (pixel coordinates (x, y) [M, 2], camera z [M]); pixels of points at
    or behind the camera plane are NaN (z is kept, so callers can test z > near)."""
    cam = points.astype(np.float64) @ viewmat[:3, :3].T.astype(np.float64) + viewmat[:3, 3].astype(np.float64)
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pix = cam @ K.T.astype(np.float64)
        xy = pix[:, :2] / pix[:, 2:3]
    xy[z <= 0] = np.nan
    return xy, z
