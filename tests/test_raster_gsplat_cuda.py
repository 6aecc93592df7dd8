"""The gsplat backend on a real GPU: same images, depths, alphas and gradients as the cpu backend.

Skipped unless CUDA is available and gsplat imports (the test machines have neither; the CPU
tests of the plumbing around gsplat's calls are in test_raster_gsplat.py). On a GPU machine:

    pip install gsplat==1.5.3 && python -m pytest -q tests/test_raster_gsplat_cuda.py -s

gsplat is built with `-use_fast_math`, so its exp() and divisions round differently from torch's:
values are compared at 1e-4 (the cpu backend's own tolerance is 1e-5) and gradients at 1e-3 of
their largest entry plus 1e-2 relative. Rounding also flips a few discrete decisions (a Gaussian
exactly at the 1/255 alpha cut-off or the transmittance stop): on an H200, 3 of 19,200 pixels of
the RGB case differed by up to 5e-4 (alpha 9e-4), so at most 0.1% of the pixels may exceed 1e-4,
and none 1e-2. The worst differences are printed (`-s`).
"""
from __future__ import annotations

import importlib.util

import pytest
import torch

from baselines.render import rasterize
from raster_cases import hard_cases, random_scene, weighted_loss

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available() or importlib.util.find_spec("gsplat") is None,
    reason="needs a CUDA device and gsplat (pip install gsplat)",
)

VALUE_ATOL = 1e-4
FLIPPED_PIXELS = 1e-3  # share of pixels allowed past VALUE_ATOL (decisions flipped by rounding) ...
FLIPPED_ATOL = 1e-2  # ... and how far past
GRAD_FRACTION = 1e-3
GRAD_RTOL = 1e-2
KEYS = ("means", "quats", "scales", "opacities", "features")


def _render(scene, backend: str, device: str) -> dict[str, torch.Tensor]:
    tensors = {k: v.detach().to(device).requires_grad_() for k, v in scene.gaussian_tensors.items()}
    background = None if scene.background is None else scene.background.to(device)
    image, depth, alpha, meta = rasterize(tensors["means"], tensors["quats"], tensors["scales"], tensors["opacities"],
                                          tensors["features"], scene.viewmat.to(device), scene.K.to(device),
                                          scene.width, scene.height, backend=backend, background=background)
    assert meta.backend == backend
    weighted_loss((image.cpu(), depth.cpu(), alpha.cpu()), seed=3).backward()
    out = {"image": image, "depth": depth, "alpha": alpha}
    out.update({k: v.grad for k, v in tensors.items()})
    return {k: v.detach().cpu() for k, v in out.items()}


@pytest.mark.parametrize("channels,n,size", [(3, 3000, (160, 120)), (12, 800, (97, 61)), (600, 200, (48, 40))],
                         ids=["rgb", "flow_channels", "split_calls"])
def test_gsplat_on_cuda_matches_the_cpu_backend(channels, n, size):
    scene = random_scene(n, *size, channels=channels, seed=11, pixel_sigma=(0.5, 4.0))
    scene.background = torch.rand(channels, generator=torch.Generator().manual_seed(2))
    got, want = _render(scene, "gsplat", "cuda"), _render(scene, "cpu", "cpu")
    failures, report = [], []
    for key in ("image", "alpha", "depth"):
        diff = (got[key] - want[key]).abs()
        scale = 1.0 if key != "depth" else float(want[key].abs().max())
        over = int((diff > VALUE_ATOL * scale).sum())
        report.append(f"{key} {float(diff.max()):.2e} (pixels over tolerance: {over})")
        if over > FLIPPED_PIXELS * diff[..., 0].numel() or float(diff.max()) > FLIPPED_ATOL * scale:
            failures.append(f"{key}: max |gsplat - cpu| = {float(diff.max()):.3g}, {over} values over {VALUE_ATOL}")
    for key in KEYS:
        g, w = got[key], want[key]
        largest = float(w.abs().max())
        excess = (g - w).abs() - GRAD_RTOL * w.abs()
        report.append(f"d{key} {float((g - w).abs().max()) / max(largest, 1e-30):.2e} "
                      f"(over: {int((excess > GRAD_FRACTION * largest).sum())} of {w.numel()})")
        if not torch.isfinite(g).all():
            failures.append(f"{key} gradient not finite")
        elif float(excess.max()) > GRAD_FRACTION * largest:
            failures.append(f"{key} gradient: {float(excess.max()):.3g} over, max {largest:.3g}")
    print(f"\n[gsplat vs cpu, {channels} channels, {n} Gaussians] worst |diff| (gradients relative to their max): "
          + ", ".join(report), flush=True)
    assert not failures, "; ".join(failures)


@pytest.mark.parametrize("case", hard_cases(), ids=lambda c: c.name)
def test_hard_cases_stay_finite_on_gsplat(case):
    got = _render(case.scene, "gsplat", "cuda")
    for key, value in got.items():
        assert torch.isfinite(value).all(), f"{case.name}: {key} not finite"
