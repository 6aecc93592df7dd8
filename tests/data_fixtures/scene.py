"""The fixture scene: a textured back wall, floor, a static panel and one moving panel, seen by
a laterally moving camera. Known cameras (OpenCV axes, world->camera) and ground-truth geometry.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .render import Quad, RenderedFrame, render, smooth_noise_texture


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World->camera 4x4 (OpenCV axes) for a camera at `centre` looking at `target`; world y is down."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    viewmat = np.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ centre
    return viewmat


@dataclass
class FixtureScene:
    quads: list[Quad]
    K: np.ndarray  # [3,3] at (width, height)
    viewmats: np.ndarray  # [N,4,4] world->camera
    times: np.ndarray  # [N]
    width: int
    height: int
    near: float
    far: float
    background: float = 0.5
    supersample: int = 2

    @property
    def num_frames(self) -> int:
        return len(self.viewmats)

    def render(self, i: int, blank: bool = False) -> RenderedFrame:
        frame = render(self.quads, self.K, self.viewmats[i], self.width, self.height, float(self.times[i]),
                       background=self.background, supersample=self.supersample)
        if blank:
            frame.rgb[:] = 0.5
        return frame

    def static_distance(self, points: np.ndarray) -> np.ndarray:
        """[P] distance from points [P,3] to the nearest static quad."""
        return np.min([q.distance(points) for q in self.quads if not q.dynamic], axis=0)

    def dynamic_distance(self, points: np.ndarray, samples: int = 21) -> np.ndarray:
        """[P] distance to the region swept by the moving quads over t in [0, 1]."""
        return np.min([q.distance(points, t) for q in self.quads if q.dynamic
                       for t in np.linspace(0, 1, samples)], axis=0)


def make_scene(num_frames: int = 8, width: int = 96, height: int = 96, seed: int = 0,
               focal: float = 80.0) -> FixtureScene:
    rng = np.random.default_rng(seed)
    tex = lambda tint=(1, 1, 1), size=48: smooth_noise_texture(rng, size, 1.2, tint)  # noqa: E731
    quads = [
        # back wall z = 6
        Quad(np.array([-5.0, -4.0, 6.0]), np.array([10.0, 0, 0]), np.array([0, 8.0, 0]), tex(size=64)),
        # floor y = 1.5 (world y is down)
        Quad(np.array([-5.0, 1.5, 1.0]), np.array([10.0, 0, 0]), np.array([0, 0, 5.0]), tex((0.9, 0.8, 0.7), 40)),
        # static panel at z = 4, left
        Quad(np.array([-2.0, -1.0, 4.0]), np.array([1.4, 0, 0]), np.array([0, 2.5, 0]), tex((1.0, 0.6, 0.6), 20)),
        # moving panel at z = 3.5, right, sliding in +x
        Quad(np.array([0.4, -0.8, 3.5]), np.array([1.2, 0, 0]), np.array([0, 1.6, 0]), tex((0.5, 0.7, 1.0), 20),
             velocity=np.array([0.0, 0.0, -0.3])),
    ]
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], np.float64)
    xs = np.linspace(-0.8, 0.8, num_frames)
    viewmats = np.stack([
        look_at(np.array([x, -0.2 + 0.1 * np.sin(3 * x), 0.1 * x]), np.array([0.0, 0.3, 5.0]))
        for x in xs])
    times = np.linspace(0.0, 1.0, num_frames)
    return FixtureScene(quads, K, viewmats, times, width, height, near=2.0, far=9.0)


MARKER_POINT = np.array([0.1, -0.05, 3.0])


def make_marker_scene(num_frames: int = 3, width: int = 64, height: int = 64) -> FixtureScene:
    """A small Gaussian spot centred on `MARKER_POINT`, on black. The spot is a few pixels wide,
    so the intensity centroid of each image is the spot's projection to well below 0.05 px at
    full and half resolution: an independent check of axes and the pixel-centre convention."""
    scene = make_scene(num_frames=num_frames, width=width, height=height, focal=80.0 * width / 96)
    half = 0.15
    texels = (np.arange(64) + 0.5) / 64 - 0.5
    spot = np.exp(-(texels[:, None] ** 2 + texels[None, :] ** 2) / (2 * 0.15 ** 2)).astype(np.float32)
    scene.quads = [Quad(MARKER_POINT - np.array([half, half, 0.0]), np.array([2 * half, 0, 0]),
                        np.array([0, 2 * half, 0]), np.repeat(spot[..., None], 3, axis=2))]
    scene.background, scene.supersample = 0.0, 4
    return scene
