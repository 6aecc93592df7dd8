"""Shared scene builders, hard cases and the compositor registry for the rasterizer tests.

`CPU_COMPOSITORS` lists (as pytest params) the compositing functions of the cpu backend, with the
backend signature `(projection, opacities [N], features [N, C], width, height) -> (image [H,W,C],
alpha [H,W,1])`: the torch tiled path and the compiled kernel (skipped, with the reason, where the
kernel cannot build). Every backend-equality and hard-case test is parametrized over it, so a new
CPU implementation is tested by adding one entry.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import pytest
import torch
from torch import Tensor

from baselines.render.api import _composite
from baselines.render.backends import Backend
from baselines.render.composite_reference import composite_reference
from baselines.render.composite_tiled import composite_tiled
from baselines.render.kernel import composite_kernel, kernel_available
from baselines.render.projection import Projection, max_extend_for_opacity, project_gaussians_torch


_KERNEL_OK, _KERNEL_REASON = kernel_available()
# Skips where the kernel cannot build (no compiler, REFLOW4DGS_CPU_KERNEL=0, ...). A build that
# fails although a compiler is present is an error, reported by test_raster_kernel.py.
requires_kernel = pytest.mark.skipif(not _KERNEL_OK, reason=f"compiled CPU kernel unavailable: {_KERNEL_REASON}")

CPU_COMPOSITORS = [pytest.param(composite_tiled, id="torch_tiled"),
                   pytest.param(composite_kernel, id="kernel", marks=requires_kernel)]
# The oracle plus every CPU implementation: for tests that every compositor must pass alike.
ALL_COMPOSITORS = [pytest.param(composite_reference, id="reference"), *CPU_COMPOSITORS]
over_cpu_compositors = pytest.mark.parametrize("compositor", CPU_COMPOSITORS)
over_all_compositors = pytest.mark.parametrize("compositor", ALL_COMPOSITORS)


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
    cases.extend(_crowded_hard_cases(w, h))
    return cases


def _crowded_hard_cases(w: int, h: int) -> list[HardCase]:
    """Extreme Gaussians among many ordinary ones (so every tile list mixes both)."""
    g = torch.Generator().manual_seed(5)
    base = random_scene(60, w, h, seed=1, posed=False)
    # Depths around the near plane 0.01 (inclusive): behind, at the camera, inside, just past it.
    z = torch.tensor([-1.0, -0.005, 0.0, 0.008, 0.02, 0.05, 0.3])
    near_plane_scan = _append(base, means=torch.stack([torch.full_like(z, 0.01), torch.full_like(z, -0.01), z], 1),
                              scales=torch.full((7, 3), 0.1), opacities=torch.full((7,), 0.8),
                              features=torch.rand(7, 3, generator=g))
    # Needles (1e-8) and giants (1e4), isotropic and mixed, randomly rotated.
    needles_and_giants = _append(
        random_scene(60, w, h, seed=2, posed=False),
        means=torch.tensor([[0.0, 0.0, 3.0], [0.1, 0.1, 4.0], [0.0, 0.0, 20.0], [0.0, 0.0, 5.0]]),
        scales=torch.tensor([[1e-8] * 3, [1e-8, 1e-8, 1.0], [1e4] * 3, [1e4, 1e-8, 1e-8]]),
        opacities=torch.tensor([0.9, 0.5, 0.02, 0.3]), features=torch.rand(4, 3, generator=g),
        quats=torch.randn(4, 4, generator=g))
    # Opacities exactly 0 and 1 alternating: the 0.999 clamp and stops in many pixels at once.
    zero_and_one = random_scene(80, w, h, seed=3, posed=False, pixel_sigma=(2.0, 4.0))
    zero_and_one.opacities = (torch.arange(80) % 2 == 0).float()
    # Every Gaussian in front of the camera but beside the image: nothing to bin although N > 0.
    beside = random_scene(50, w, h, seed=4, posed=False)
    beside.means = beside.means + torch.tensor([50.0, 0.0, 0.0])
    return [
        HardCase("near_plane_scan", near_plane_scan, "the last 7 Gaussians scan z across the near plane"),
        HardCase("needles_and_giants", needles_and_giants, "the last 4 Gaussians"),
        HardCase("opacity_zero_and_one", zero_and_one),
        HardCase("all_off_screen", beside),
        HardCase("stack_1000_depth_ties", _stack_with_depth_ties(), "an image smaller than one tile"),
    ]


def _append(scene: Scene, means: Tensor, scales: Tensor, opacities: Tensor, features: Tensor,
            quats: Tensor | None = None) -> Scene:
    """`scene` with K more Gaussians (camera-frame means when the scene's camera is the identity)."""
    if quats is None:
        quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(means.shape[0], 1)
    extra = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "features": features}
    joined = {k: torch.cat([v, extra[k].to(v.dtype)]) for k, v in scene.gaussian_tensors.items()}
    return Scene(viewmat=scene.viewmat, K=scene.K, width=scene.width, height=scene.height, **joined)


def _stack_with_depth_ties(n: int = 1000, seed: int = 4) -> Scene:
    """n Gaussians around one pixel, a few pixels wide, at depths tied in groups of 4 (early stop)."""
    g = torch.Generator().manual_seed(seed)
    width, height, focal = 14, 11, 14.0
    depth = 2.0 + torch.arange(n, dtype=torch.float32).div(4).floor() * 0.01
    offset = 0.02 * torch.randn(n, 2, generator=g)
    means = torch.cat([offset * depth[:, None] / focal, depth[:, None]], dim=1)
    scales = (0.5 + torch.rand(n, 3, generator=g)) * 5.0 * depth[:, None] / focal
    return camera_space_scene(means, scales, 0.2 + 0.6 * torch.rand(n, generator=g), torch.rand(n, 3, generator=g),
                              width, height, focal=focal, quats=torch.randn(n, 4, generator=g))


HARD_CASES = {case.name: case for case in hard_cases()}

# Random scenes for the backend-equality tests (random_scene keyword arguments): image sizes not
# divisible by 16 (partial border tiles), whole tiles only, a single tile; C = 1, 3 and 10; a deep
# scene of opaque Gaussians where most pixels reach the transmittance stop.
RANDOM_SCENES = {
    "120g_45x37_c1": dict(n=120, width=45, height=37, channels=1, seed=0, pixel_sigma=(0.5, 3.0)),
    "400g_70x50_c3": dict(n=400, width=70, height=50, channels=3, seed=1, pixel_sigma=(0.5, 3.0)),
    "250g_33x61_c10": dict(n=250, width=33, height=61, channels=10, seed=2, pixel_sigma=(0.5, 3.0)),
    "deep_500g_40x23_c3": dict(n=500, width=40, height=23, channels=3, seed=3, opacity=(0.5, 0.99),
                               pixel_sigma=(1.0, 4.0)),
    "300g_64x48_c3": dict(n=300, width=64, height=48, channels=3, seed=5, pixel_sigma=(0.5, 3.0)),
    "120g_16x16_c3": dict(n=120, width=16, height=16, channels=3, seed=6, pixel_sigma=(0.5, 3.0)),
}


def named_scene(name: str) -> Scene:
    """A scene of HARD_CASES or RANDOM_SCENES by name (a fresh copy each call)."""
    if name in HARD_CASES:
        return HARD_CASES[name].scene.to(HARD_CASES[name].scene.means.dtype)
    return random_scene(**RANDOM_SCENES[name])


@functools.lru_cache(maxsize=None)
def reference_grads(name: str) -> dict[str, Tensor]:
    """composite_grads of the dense reference on a named scene, computed once per session."""
    return composite_grads(composite_reference, named_scene(name))


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


GRAD_NOISE_FRACTION = 1e-6  # floor: float32 rounding of the largest gradient terms (~8 eps)


def assert_grads_close(actual: Tensor, expected: Tensor, name: str, noise_floor: float = 1e-12) -> None:
    """Per-element |a - e| <= max(GRAD_ATOL_FRACTION * max|e|, noise_floor) + GRAD_RTOL * |e|.

    `noise_floor` covers gradients that vanish analytically (e.g. quaternion gradients of
    isotropic Gaussians): what remains is rounding noise of the terms that cancel, which scales
    with the problem's largest gradients, not with the vanishing one.
    """
    atol = GRAD_ATOL_FRACTION * float(expected.abs().max()) if expected.numel() else 0.0
    torch.testing.assert_close(actual, expected, rtol=GRAD_RTOL, atol=max(atol, noise_floor, 1e-12),
                               msg=lambda m: f"{name}: {m}")


def weighted_loss(outputs: tuple[Tensor, ...], seed: int = 0) -> Tensor:
    """sum_k <outputs[k], random weights>: a loss whose gradient exercises every pixel and channel."""
    g = torch.Generator().manual_seed(seed)
    return sum((t * torch.randn(t.shape, generator=g, dtype=t.dtype)).sum() for t in outputs)


def composite_grads(compositor, scene: Scene, seed: int = 0) -> dict[str, Tensor]:
    """Image, alpha and the gradients of a weighted loss through projection + `compositor`.

    Returns a dict with "image", "alpha" and the gradients "means", "quats", "scales",
    "opacities", "features" (the 3D parameters) and "means2d", "conics" (the compositor's
    geometric inputs).
    """
    scene = scene.to(scene.means.dtype).requires_grad_()
    proj = project(scene)
    proj.means2d.retain_grad()
    proj.conics.retain_grad()
    image, alpha = compositor(proj, scene.opacities, scene.features, scene.width, scene.height)
    weighted_loss((image, alpha), seed).backward()
    out = {"image": image.detach(), "alpha": alpha.detach(), "means2d": proj.means2d.grad, "conics": proj.conics.grad}
    out.update({k: v.grad for k, v in scene.gaussian_tensors.items()})
    return out


VALUE_ATOL = 1e-5  # float32 image and alpha: two summation orders of at most a few hundred terms
GRAD_KEYS = ("means", "quats", "scales", "opacities", "features", "means2d", "conics")


def assert_matches(result: dict[str, Tensor], expected: dict[str, Tensor], value_atol: float = VALUE_ATOL) -> None:
    """Finite, and image/alpha within value_atol and every gradient within assert_grads_close."""
    for key in ("image", "alpha") + GRAD_KEYS:
        assert result[key] is not None, f"no gradient reached {key}"
        assert torch.isfinite(result[key]).all(), f"{key} is not finite"
    for key in ("image", "alpha"):
        torch.testing.assert_close(result[key], expected[key], atol=value_atol, rtol=0, msg=lambda m: f"{key}: {m}")
    largest = max((float(expected[k].abs().max()) for k in GRAD_KEYS if expected[k].numel()), default=0.0)
    for key in GRAD_KEYS:
        assert_grads_close(result[key], expected[key], key, noise_floor=GRAD_NOISE_FRACTION * largest)
