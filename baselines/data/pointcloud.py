"""`PointCloud`, point-file readers (PLY, NPY, COLMAP) and colouring points from images."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import DatasetError


@dataclass
class PointCloud:
    """Points [P,3] float32, colours [P,3] float32 in [0, 1], optional normals [P,3] float32."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = self._checked("points", self.points)
        self.colors = self._checked("colors", self.colors)
        if len(self.colors) != len(self.points):
            raise DatasetError(f"PointCloud: {len(self.points)} points but {len(self.colors)} colours")
        if len(self.colors) and (self.colors.min() < 0 or self.colors.max() > 1):
            raise DatasetError("PointCloud: colours must lie in [0, 1]")
        if self.normals is not None:
            self.normals = self._checked("normals", self.normals)
            if len(self.normals) != len(self.points):
                raise DatasetError(f"PointCloud: {len(self.points)} points but {len(self.normals)} normals")

    @staticmethod
    def _checked(name: str, array: np.ndarray) -> np.ndarray:
        array = np.asarray(array, dtype=np.float32)
        if array.ndim != 2 or array.shape[1] != 3:
            raise DatasetError(f"PointCloud.{name} has shape {array.shape}, expected [P, 3]")
        if not np.isfinite(array).all():
            raise DatasetError(f"PointCloud.{name} holds non-finite values")
        return np.ascontiguousarray(array)

    def __len__(self) -> int:
        return len(self.points)

    def subsample(self, max_points: int, seed: int = 0) -> "PointCloud":
        """A random subset of at most `max_points` points (self when already small enough)."""
        if len(self) <= max_points:
            return self
        keep = np.sort(np.random.default_rng(seed).choice(len(self), max_points, replace=False))
        return PointCloud(self.points[keep], self.colors[keep],
                          None if self.normals is None else self.normals[keep])

    def transformed(self, center: np.ndarray, scale: float) -> "PointCloud":
        """Points mapped by p -> (p - center) * scale (normals unchanged)."""
        return PointCloud((self.points - np.asarray(center, np.float32)) * np.float32(scale),
                          self.colors, self.normals)


def _colours_to_unit(colours: np.ndarray, source: Path) -> np.ndarray:
    """Colours as float in [0, 1] from uint8 or float storage (floats above 1 are taken as 0..255)."""
    if np.issubdtype(colours.dtype, np.integer):
        return colours.astype(np.float32) / 255.0
    colours = colours.astype(np.float32)
    if not np.isfinite(colours).all():
        raise DatasetError(f"non-finite colours in {source}")
    if colours.max(initial=0.0) > 1.0:
        colours = colours / 255.0
    if colours.min(initial=0.0) < 0.0 or colours.max(initial=0.0) > 1.0:
        raise DatasetError(f"colours in {source} are outside [0, 1] and [0, 255]")
    return colours


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(points [P,3], colours [P,3] in [0,1] or None, normals [P,3] or None) from a PLY file."""
    from plyfile import PlyData

    try:
        vertex = PlyData.read(str(path))["vertex"]
        names = vertex.data.dtype.names
        points = np.stack([vertex[k] for k in ("x", "y", "z")], axis=1)
    except Exception as exc:  # plyfile raises several unrelated types on malformed input
        raise DatasetError(f"cannot read point file {path}: {exc}") from exc
    colours = normals = None
    if all(k in names for k in ("red", "green", "blue")):
        colours = _colours_to_unit(np.stack([vertex[k] for k in ("red", "green", "blue")], 1), path)
    if all(k in names for k in ("nx", "ny", "nz")):
        normals = np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1)
    return points, colours, normals


def read_npy_points(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(points [P,3], colours or None) from an .npy of shape [P,3] (xyz) or [P,6] (xyz + rgb)."""
    from .validation import load_npy

    array = load_npy(path)
    if array.ndim != 2 or array.shape[1] not in (3, 6):
        raise DatasetError(f"{path}: point array has shape {array.shape}, expected [P, 3] or [P, 6]")
    colours = _colours_to_unit(array[:, 3:6], path) if array.shape[1] == 6 else None
    return array[:, :3], colours


def read_colmap_points(model_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points [P,3], colours [P,3] in [0,1]) of a COLMAP model folder (bin or txt)."""
    from .colmap_compat import read_reconstruction

    reconstruction = read_reconstruction(model_dir)
    points3d = list(reconstruction.points3D.values())
    points = np.array([p.xyz for p in points3d], np.float64).reshape(-1, 3)
    colours = np.array([p.color for p in points3d], np.float32).reshape(-1, 3) / 255.0
    return points, colours


def read_point_file(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Dispatch on the file type: .ply, .npy, or a COLMAP model folder / points3D.{bin,txt}."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        return read_ply(path)
    if path.suffix.lower() == ".npy":
        return (*read_npy_points(path), None)
    if path.is_dir() or path.name.lower() in ("points3d.bin", "points3d.txt"):
        return (*read_colmap_points(path if path.is_dir() else path.parent), None)
    raise DatasetError(f"unsupported point file {path} (expected .ply, .npy or a COLMAP model)")


def project_to_pixels(points: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where points [P,3] land in ``camera``'s image.

    Returns (in_front [P] bool, inside [P] bool: in front and within the image, col [P], row [P]
    int64 pixel indices, -1 for points behind the camera).
    """
    viewmat = camera.viewmat.detach().cpu().double().numpy()
    K = camera.K.detach().cpu().double().numpy()
    cam_pts = np.asarray(points, np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam_pts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam_pts @ K.T)[:, :2] / z[:, None]
    in_front = (z > 1e-6) & np.isfinite(uv).all(axis=1)
    uv = np.clip(np.where(in_front[:, None], uv, -1.0), -1.0, 2.0**30)  # warning-free int cast
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = in_front & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    return in_front, inside, col, row


def sample_colours(points: np.ndarray, cameras: Sequence, max_views: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Colour points [P,3] from the images of `cameras` (those with an image).

    Each point takes the per-channel median of the pixels it projects to (in front of the
    camera, inside the image) over up to `max_views` evenly spread views. Occlusion is not
    tested; the median over several views suppresses most wrong samples.

    Returns (colours [P,3] float32 in [0,1], found [P] bool); points seen by no view get 0.5.
    """
    views = [c for c in cameras if c.image is not None]
    if len(views) > max_views:
        views = [views[i] for i in np.linspace(0, len(views) - 1, max_views).round().astype(int)]
    samples = np.full((len(views), len(points), 3), np.nan, np.float32)
    for v, cam in enumerate(views):
        _, ok, col, row = project_to_pixels(points, cam)
        image = cam.image.detach().cpu().numpy()
        samples[v, ok] = image[row[ok], col[ok]]
    found = np.isfinite(samples[..., 0]).any(axis=0)
    colours = np.full((len(points), 3), 0.5, np.float32)
    if found.any():
        colours[found] = np.nanmedian(samples[:, found], axis=0)
    return np.clip(colours, 0.0, 1.0), found


@dataclass
class RawPoints:
    """A dataset point file as read (validated early), before colours are completed from images."""

    path: Path
    points: np.ndarray
    colors: np.ndarray | None
    normals: np.ndarray | None

    @classmethod
    def read(cls, path: Path) -> "RawPoints":
        from .validation import require_finite

        points, colours, normals = read_point_file(path)
        points = require_finite(np.asarray(points), path, "point coordinate")
        if len(points) == 0:
            raise DatasetError(f"point file {path} holds no points")
        if normals is not None:
            normals = require_finite(np.asarray(normals), path, "normal")
        return cls(Path(path), points, colours, normals)

    def transformed(self, center: np.ndarray, scale: float) -> "RawPoints":
        """Points mapped by p -> (p - center) * scale."""
        return RawPoints(self.path, (self.points - np.asarray(center)) * scale, self.colors, self.normals)

    def to_point_cloud(self, cameras: Sequence) -> PointCloud:
        """The `PointCloud`, colouring points from the cameras' images when the file has no colours."""
        colours = self.colors
        if colours is None:
            colours, _ = sample_colours(self.points, cameras)
        return PointCloud(self.points, colours, self.normals)
