"""The analytic renderer: cast camera rays against placed unit shapes, shade the hits.

Ray directions are built as ``R_c2w K^-1 [u, v, 1]``, i.e. with camera-space z component 1, so
the ray parameter of a hit IS the camera z-depth of the hit (the ``depth`` the outputs store).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .lighting import LightState
from .objects import SceneObject
from .scene import Placement
from .shapes import intersect, local_normal
from .textures import albedo
from .transforms import rigid_inverse

# Cull a shape with its bounding sphere only when that leaves at most this fraction of the rays;
# otherwise gathering the subset costs more than it saves.
_CULL_FRACTION = 0.6


@dataclass(frozen=True)
class FrameCamera:
    """A pinhole camera of one frame.

    Attributes:
        K: [3,3] intrinsics (pixels). c2w: [4,4] camera-to-world (OpenCV axes).
        width, height: image size. time: frame time in [0, 1]. camera_id: physical camera.
    """

    K: np.ndarray
    c2w: np.ndarray
    width: int
    height: int
    time: float
    camera_id: int

    @property
    def viewmat(self) -> np.ndarray:
        """[4,4] world-to-camera."""
        return rigid_inverse(self.c2w)

    @property
    def center(self) -> np.ndarray:
        return self.c2w[:3, 3]

    def directions(self, pixels: np.ndarray) -> np.ndarray:
        """World ray directions [M,3] (camera z component 1) through image points [M,2] (x, y)."""
        homog = np.concatenate([pixels, np.ones((len(pixels), 1))], axis=1)
        return homog @ (self.c2w[:3, :3] @ np.linalg.inv(self.K)).T

    def pixel_grid(self, offsets: Sequence[tuple[float, float]] = ((0.5, 0.5),)) -> np.ndarray:
        """Image points [H*W*S, 2]: for pixel (i, j) in row-major order, then each of the S
        sub-pixel offsets (x, y) within the pixel; (0.5, 0.5) is the pixel centre."""
        jj, ii = np.meshgrid(np.arange(self.width, dtype=np.float64),
                             np.arange(self.height, dtype=np.float64))
        offs = np.asarray(offsets, dtype=np.float64)  # [S, 2]
        x = jj.reshape(-1, 1) + offs[None, :, 0]
        y = ii.reshape(-1, 1) + offs[None, :, 1]
        return np.stack([x.reshape(-1), y.reshape(-1)], axis=1)


@dataclass
class Hits:
    """First hits of M rays: ``depth`` [M] (inf = miss), ``index`` [M] int32 object index (-1 =
    miss), ``local`` [M,3] unit-shape coordinates of the hit point (0 for misses)."""

    depth: np.ndarray
    index: np.ndarray
    local: np.ndarray


def _bounding_candidates(place: Placement, origin: np.ndarray, dirs: np.ndarray,
                         dd: np.ndarray) -> np.ndarray:
    """Bool [M]: rays that meet the placement's bounding sphere in front of the origin."""
    oc = place.center - origin
    proj = dirs @ oc
    disc = proj * proj - dd * (float(oc @ oc) - place.radius ** 2)
    return (disc >= 0.0) & (proj + np.sqrt(np.maximum(disc, 0.0)) > 0.0)


def cast(placements: Sequence[Placement], origin: np.ndarray, dirs: np.ndarray) -> Hits:
    """Nearest hit of rays ``origin + s * dirs`` [M,3] among the present placements."""
    m = len(dirs)
    depth = np.full(m, np.inf)
    index = np.full(m, -1, dtype=np.int32)
    origin_h = np.append(origin, 1.0)
    dd = np.einsum("ij,ij->i", dirs, dirs)
    for place in placements:
        if not place.present:
            continue
        rows = None
        if np.isfinite(place.radius):
            candidate = _bounding_candidates(place, origin, dirs, dd)
            count = int(candidate.sum())
            if count == 0:
                continue
            if count <= _CULL_FRACTION * m:
                rows = np.flatnonzero(candidate)
        local_o = (place.to_local @ origin_h)[:3]
        sub_dirs = dirs if rows is None else dirs[rows]
        s = intersect(place.shape, local_o, sub_dirs @ place.to_local[:3, :3].T)
        if rows is None:
            closer = s < depth
            depth[closer] = s[closer]
            index[closer] = place.index
        else:
            closer = s < depth[rows]
            depth[rows[closer]] = s[closer]
            index[rows[closer]] = place.index
    local = np.zeros((m, 3))
    by_index = {p.index: p for p in placements}
    for k in np.unique(index[index >= 0]):
        rows = np.flatnonzero(index == k)
        place = by_index[int(k)]
        local_o = (place.to_local @ origin_h)[:3]
        local[rows] = local_o + depth[rows, None] * (dirs[rows] @ place.to_local[:3, :3].T)
    return Hits(depth=depth, index=index, local=local)


def shade(hits: Hits, dirs: np.ndarray, placements: Sequence[Placement],
          objects: Sequence[SceneObject], texture_seeds: Sequence[int],
          light: LightState) -> np.ndarray:
    """Colour [M,3] of the hits (black for misses): texture albedo times Lambertian shading,
    with normals turned towards the viewer (all surfaces are two-sided)."""
    color = np.zeros((len(dirs), 3))
    by_index = {p.index: p for p in placements}
    for k in np.unique(hits.index[hits.index >= 0]):
        k = int(k)
        rows = np.flatnonzero(hits.index == k)
        place, obj = by_index[k], objects[k]
        points = hits.local[rows]
        base = albedo(obj.texture, points * np.asarray(obj.size), texture_seeds[k])
        # Normals transform with the inverse transpose of the linear part: n_w = A^-T n_l.
        normals = local_normal(place.shape, points) @ place.to_local[:3, :3]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        facing = np.einsum("ij,ij->i", normals, dirs[rows])
        normals[facing > 0.0] *= -1.0
        color[rows] = light.shade(base, normals)
    return np.clip(color, 0.0, 1.0)
