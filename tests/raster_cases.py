"""Shared scene builders, hard cases and the compositor registry for the rasterizer tests.

`CPU_COMPOSITORS` maps a name to a compositing function with the backend signature
`(projection, opacities [N], features [N, C], width, height) -> (image [H,W,C], alpha [H,W,1])`.
Every backend-equality and hard-case test is parametrized over it, so a new CPU implementation
(the compiled kernel) is tested by adding one entry.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from baselines.render.api import _composite
from baselines.render.backends import Backend
from baselines.render.composite_reference import composite_reference
from baselines.render.composite_tiled import composite_tiled
from baselines.render.projection import Projection, max_extend_for_opacity, project_gaussians_torch

CPU_COMPOSITORS = {"torch_tiled": composite_tiled}
# The oracle plus every CPU implementation: for tests that every compositor must pass alike.
ALL_COMPOSITORS = {"reference": composite_reference, **CPU_COMPOSITORS}


@dataclass
class Scene:
    """Inputs of one `rasterize` call (activated parameters)."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor
    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    background: Tensor | None = None

    @property
    def gaussian_tensors(self) -> dict[str, Tensor]:
        return {"means": self.means, "quats": self.quats, "scales": self.scales,
                "opacities": self.opacities, "features": self.features}

    def args(self) -> tuple:
        return (self.means, self.quats, self.scales, self.opacities, self.features, self.viewmat, self.K,
                self.width, self.height)

    def requires_grad_(self) -> "Scene":
        for t in self.gaussian_tensors.values():
            t.requires_grad_(True)
        return self

    def to(self, dtype: torch.dtype) -> "Scene":
        cast = {k: v.detach().to(dtype) for k, v in self.gaussian_tensors.items()}
        return Scene(viewmat=self.viewmat.to(dtype), K=self.K.to(dtype), width=self.width, height=self.height,
                     background=None if self.background is None else self.background.to(dtype), **cast)


def intrinsics(width: int, height: int, focal: float | None = None, dtype=torch.float32) -> Tensor:
    """Pinhole K with the principal point at the image centre (focal defaults to the width)."""
    f = float(width if focal is None else focal)
    return torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]], dtype=dtype)


def look_from(position: Tensor, rotation: Tensor) -> Tensor:
    """World-to-camera [4,4] for a camera at `position` whose camera-to-world rotation is `rotation`."""
    viewmat = torch.eye(4, dtype=position.dtype)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3] = -rotation.T @ position
    return viewmat


def random_rotation(generator: torch.Generator, dtype=torch.float32) -> Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=generator, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q.to(dtype)


def random_scene(
    n: int,
    width: int,
    height: int,
    channels: int = 3,
    seed: int = 0,
    pixel_sigma: tuple[float, float] = (0.5, 6.0),
    opacity: tuple[float, float] = (0.05, 0.99),
    depth: tuple[float, float] = (2.0, 8.0),
    margin: float = 0.15,
    posed: bool = True,
    dtype: torch.dtype = torch.float32,
) -> Scene:
    """Gaussians in front of a camera, each a few pixels wide on screen (a trained model's scale).

    Means are drawn in the camera frustum (with `margin` of the image size beyond each border,
    so some boxes straddle the edges), screen-space standard deviations log-uniform in
    `pixel_sigma`, random rotations and anisotropy, opacities uniform in `opacity`. With `posed`
    the camera has a random pose (a non-identity viewmat).
    """
    g = torch.Generator().manual_seed(seed)
    K = intrinsics(width, height, dtype=torch.float64)
    z = torch.empty(n, dtype=torch.float64).uniform_(*depth, generator=g)
    u = torch.empty(n, dtype=torch.float64).uniform_(-margin * width, (1 + margin) * width, generator=g)
    v = torch.empty(n, dtype=torch.float64).uniform_(-margin * height, (1 + margin) * height, generator=g)
    cam = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], dim=-1)
    lo, hi = math.log(pixel_sigma[0]), math.log(pixel_sigma[1])
    sigma_px = torch.exp(torch.empty(n, 1, dtype=torch.float64).uniform_(lo, hi, generator=g))
    aniso = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(-0.7, 0.7, generator=g))
    scales = sigma_px * aniso * z[:, None] / K[0, 0]
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = torch.empty(n, dtype=torch.float64).uniform_(*opacity, generator=g)
    feats = torch.rand(n, channels, generator=g, dtype=torch.float64)
    if posed:
        rot = random_rotation(g, torch.float64)
        position = torch.randn(3, generator=g, dtype=torch.float64)
        means = cam @ rot.T + position
        viewmat = look_from(position, rot)
    else:
        means, viewmat = cam, torch.eye(4, dtype=torch.float64)
    return Scene(means.to(dtype), quats.to(dtype), scales.to(dtype), opac.to(dtype), feats.to(dtype),
                 viewmat.to(dtype), K.to(dtype), width, height)


def camera_space_scene(
    means_cam: Tensor, scales: Tensor, opacities: Tensor, features: Tensor, width: int, height: int,
    focal: float | None = None, quats: Tensor | None = None, dtype: torch.dtype = torch.float32,
) -> Scene:
    """A scene with the identity camera (world = camera frame) from explicit values."""
    n = means_cam.shape[0]
    if quats is None:
        quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    return Scene(*(t.to(dtype) for t in (means_cam, quats, scales, opacities, features)),
                 torch.eye(4, dtype=dtype), intrinsics(width, height, focal, dtype=dtype), width, height)


@dataclass
class HardCase:
    name: str
    scene: Scene
    note: str = field(default="")


def _point(x: float, y: float, z: float) -> list[float]:
    return [x, y, z]


def hard_cases() -> list[HardCase]:
    """Degenerate and extreme scenes; every output and every gradient must stay finite."""
    w, h = 37, 29
    f = 40.0
    cases = []

    def one(name, mean, scale, opacity, note=""):
        cases.append(HardCase(name, camera_space_scene(
            torch.tensor([mean]), torch.tensor([scale]), torch.tensor([opacity]),
            torch.tensor([[0.2, 0.5, 0.9]]), w, h, focal=f), note))

    # Mixed with an ordinary Gaussian so that gradients are not all trivially zero.
    def with_normal(name, mean, scale, opacity, note=""):
        means = torch.tensor([mean, _point(0.05, -0.02, 2.0)])
        scales = torch.tensor([scale, [0.05, 0.03, 0.04]])
        cases.append(HardCase(name, camera_space_scene(
            means, scales, torch.tensor([opacity, 0.7]), torch.tensor([[0.2, 0.5, 0.9], [0.9, 0.1, 0.3]]),
            w, h, focal=f), note))

    with_normal("behind_camera", _point(0.1, 0.0, -2.0), [0.1, 0.1, 0.1], 0.8)
    with_normal("straddles_near_plane", _point(0.0, 0.0, 0.005), [0.5, 0.5, 0.5], 0.8, "mean inside near plane")
    with_normal("just_past_near_plane", _point(0.001, 0.0, 0.0101), [0.5, 0.5, 0.5], 0.8, "huge on screen")
    with_normal("at_camera_centre", _point(0.0, 0.0, 0.0), [0.1, 0.1, 0.1], 0.8)
    with_normal("tiny_scale", _point(0.0, 0.01, 1.5), [1e-8, 1e-8, 1e-8], 0.9)
    with_normal("huge_scale", _point(0.0, 0.0, 3.0), [1e4, 1e4, 1e4], 0.5)
    with_normal("flat_scale", _point(0.02, 0.0, 2.5), [0.2, 0.0, 0.2], 0.9, "a zero scale axis")
    with_normal("opacity_zero", _point(0.0, 0.0, 1.5), [0.05, 0.05, 0.05], 0.0)
    with_normal("opacity_one", _point(0.0, 0.0, 1.5), [0.05, 0.05, 0.05], 1.0)
    with_normal("off_screen", _point(50.0, -40.0, 2.0), [0.1, 0.1, 0.1], 0.9)
    with_normal("far_off_axis_in_front", _point(1e3, 0.0, 0.5), [0.1, 0.1, 0.1], 0.9, "Jacobian clamp")
    one("single_opacity_one", _point(0.0, 0.0, 2.0), [0.05, 0.05, 0.05], 1.0)

    # 1000 Gaussians stacked on one pixel: the transmittance stop ends each pixel early.
    n = 1000
    g = torch.Generator().manual_seed(3)
    means = torch.zeros(n, 3)
    means[:, 2] = torch.linspace(1.0, 3.0, n)
    means[:, :2] = 0.001 * torch.randn(n, 2, generator=g)
    cases.append(HardCase("stack_1000", camera_space_scene(
        means, torch.full((n, 3), 0.02), torch.full((n,), 0.6), torch.rand(n, 3, generator=g), w, h, focal=f)))

    cases.append(HardCase("empty", camera_space_scene(
        torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3), w, h, focal=f)))
    return cases


HARD_CASES = {case.name: case for case in hard_cases()}


def project(scene: Scene) -> Projection:
    """Torch projection of a scene (the projection shared by the reference and cpu backends)."""
    return project_gaussians_torch(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K,
                                   scene.width, scene.height, scene.opacities)


def screen_projection(means2d, conics, depths, opacities, width: int, height: int) -> Projection:
    """A Projection built directly in screen space (for hand-worked compositing cases).

    Args:
        means2d [N, 2], conics [N, 3] (a, b, c), depths [N], opacities [N] as nested lists or
        tensors (float32). The boxes follow the projection rule: half-extent
        ceil(extend(o) * sqrt(cov2d diagonal)), so the case is binned exactly as a projected one.
    """
    means2d = torch.as_tensor(means2d, dtype=torch.float32).reshape(-1, 2)
    conics = torch.as_tensor(conics, dtype=torch.float32).reshape(-1, 3)
    depths = torch.as_tensor(depths, dtype=torch.float32).reshape(-1)
    opacities = torch.as_tensor(opacities, dtype=torch.float32).reshape(-1)
    a, b, c = conics.double().unbind(-1)
    det = a * c - b * b
    cov2d = torch.stack([c, -b, -b, a], dim=-1).reshape(-1, 2, 2) / det[:, None, None]
    extend = torch.tensor([max_extend_for_opacity(float(o)) for o in opacities], dtype=torch.float64)
    radii = torch.ceil(extend[:, None] * torch.sqrt(torch.diagonal(cov2d, dim1=1, dim2=2)))
    m = means2d.double()
    on_screen = ((m + radii > 0) & (m - radii < torch.tensor([width, height]))).all(dim=1)
    visible = on_screen & (radii > 0).any(dim=1) & (depths > 0)
    radii = (radii * visible[:, None]).to(torch.int32)
    return Projection(means2d=means2d, cov2d=cov2d.float(), conics=conics, depths=depths, radii=radii,
                      visible=visible)


def render_with(compositor, projection: Projection, opacities: Tensor, features: Tensor, width: int, height: int,
                background: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """(features_img, depth, alpha) exactly as the public API assembles them, for one compositor."""
    backend = Backend("under_test", project_gaussians_torch, compositor)
    return _composite(backend, projection, opacities, features, width, height, background)


GRAD_RTOL = 1e-3  # float32 gradients of two summation orders (gsplat's tests use 1e-4..5e-3)
GRAD_ATOL_FRACTION = 1e-4  # absolute tolerance as a fraction of the gradient's largest entry


def assert_grads_close(actual: Tensor, expected: Tensor, name: str) -> None:
    """Per-element |a - e| <= GRAD_ATOL_FRACTION * max|e| + GRAD_RTOL * |e|."""
    atol = GRAD_ATOL_FRACTION * float(expected.abs().max()) if expected.numel() else 0.0
    torch.testing.assert_close(actual, expected, rtol=GRAD_RTOL, atol=max(atol, 1e-12), msg=lambda m: f"{name}: {m}")


def weighted_loss(outputs: tuple[Tensor, ...], seed: int = 0) -> Tensor:
    """sum_k <outputs[k], random weights>: a loss whose gradient exercises every pixel and channel."""
    g = torch.Generator().manual_seed(seed)
    return sum((t * torch.randn(t.shape, generator=g, dtype=t.dtype)).sum() for t in outputs)


def composite_grads(compositor, scene: Scene, seed: int = 0) -> dict[str, Tensor]:
    """Image, alpha and the gradients of a weighted loss through projection + `compositor`.

    Returns a dict with "image", "alpha" and the gradients "means", "quats", "scales",
    "opacities", "features", "means2d".
    """
    scene = scene.to(scene.means.dtype).requires_grad_()
    proj = project(scene)
    proj.means2d.retain_grad()
    image, alpha = compositor(proj, scene.opacities, scene.features, scene.width, scene.height)
    weighted_loss((image, alpha), seed).backward()
    out = {"image": image.detach(), "alpha": alpha.detach(), "means2d": proj.means2d.grad}
    out.update({k: v.grad for k, v in scene.gaussian_tensors.items()})
    return out
