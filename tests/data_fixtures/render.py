"""A tiny analytic ray caster of textured quads, used to generate dataset fixtures at test time.

The scene is deliberately simple (a few planar, textured rectangles; one of them moves) so that
every fixture has exact ground truth: cameras, per-pixel depth, and which pixels are dynamic.
Textures are smoothed noise, which gives SIFT enough blob-like structure even at 96x96.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass
class Quad:
    """Rectangle X = origin + s * edge_u + r * edge_v, (s, r) in [0, 1]^2, with a texture.

    `velocity` [3] moves the quad linearly with time t in [0, 1] (dynamic when non-zero).
    """

    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: np.ndarray  # [h, w, 3] float32 in [0, 1]
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def dynamic(self) -> bool:
        return bool(np.any(self.velocity != 0))

    def origin_at(self, t: float) -> np.ndarray:
        return self.origin + t * self.velocity

    def distance(self, points: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Euclidean distance [P] from points [P,3] to the rectangle at time t."""
        rel = points - self.origin_at(t)
        lu, lv = np.linalg.norm(self.edge_u), np.linalg.norm(self.edge_v)
        du, dv = self.edge_u / lu, self.edge_v / lv
        s = np.clip(rel @ du, 0.0, lu)
        r = np.clip(rel @ dv, 0.0, lv)
        closest = s[:, None] * du + r[:, None] * dv
        return np.linalg.norm(rel - closest, axis=1)


def smooth_noise_texture(rng: np.random.Generator, size: int = 64, blur: float = 1.5,
                         tint: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """[size, size, 3] float32 texture of blurred colour noise, contrast-stretched to [0, 1]."""
    noise = rng.random((size, size, 3)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), blur)
    smooth = (smooth - smooth.min()) / max(float(np.ptp(smooth)), 1e-6)
    return np.clip(smooth * np.asarray(tint, np.float32), 0.0, 1.0)


@dataclass
class RenderedFrame:
    rgb: np.ndarray  # [H,W,3] float32
    depth: np.ndarray  # [H,W] float32 z-depth (inf where nothing is hit)
    dynamic: np.ndarray  # [H,W] bool, pixel sees a moving quad


def _sample_bilinear(texture: np.ndarray, s: np.ndarray, r: np.ndarray) -> np.ndarray:
    h, w = texture.shape[:2]
    map_x = (s * w - 0.5).astype(np.float32)
    map_y = (r * h - 0.5).astype(np.float32)
    return cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def render(quads: list[Quad], K: np.ndarray, viewmat: np.ndarray, width: int, height: int,
           t: float, background: float = 0.5, supersample: int = 2) -> RenderedFrame:
    """Ray-cast the quads from a pinhole camera (OpenCV axes, pixel centres at +0.5).

    Renders at `supersample` x resolution and averages (area filter) for anti-aliasing;
    depth and the dynamic mask come from the centre sample of each output pixel.
    """
    ss = supersample
    Wh, Hh = width * ss, height * ss
    jj, ii = np.meshgrid(np.arange(Wh), np.arange(Hh))
    # A hi-res pixel centre (j+0.5)/ss in output-pixel units keeps the +0.5 convention exact.
    u = (jj + 0.5) / ss
    v = (ii + 0.5) / ss
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, tvec = viewmat[:3, :3], viewmat[:3, 3]
    centre = -R.T @ tvec
    dirs = rays_cam @ R  # rows: R^T d
    best_z = np.full((Hh, Wh), np.inf)
    rgb = np.full((Hh, Wh, 3), background, np.float32)
    dyn = np.zeros((Hh, Wh), bool)
    for quad in quads:
        o = quad.origin_at(t)
        n = np.cross(quad.edge_u, quad.edge_v)
        denom = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = ((o - centre) @ n) / denom
        hit = centre + lam[..., None] * dirs
        rel = hit - o
        s = rel @ quad.edge_u / (quad.edge_u @ quad.edge_u)
        r = rel @ quad.edge_v / (quad.edge_v @ quad.edge_v)
        z = lam  # rays_cam has unit z, so the ray parameter is the camera z-depth
        ok = np.isfinite(lam) & (lam > 1e-3) & (s >= 0) & (s <= 1) & (r >= 0) & (r <= 1) & (z < best_z)
        if not ok.any():
            continue
        colour = _sample_bilinear(quad.texture, np.where(ok, s, 0), np.where(ok, r, 0))
        rgb[ok] = colour[ok]
        best_z[ok] = z[ok]
        dyn[ok] = quad.dynamic
    out_rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    c = ss // 2
    return RenderedFrame(rgb=out_rgb, depth=best_z[c::ss, c::ss].astype(np.float32),
                         dynamic=dyn[c::ss, c::ss])
