"""The compiled CPU compositor (baselines/render/kernel.py + csrc/) against the dense oracle.

Scene builders are small functions returning the keyword arguments of `rasterize`, so they can be
folded into the shared parametrised cases. Tolerances: values 1e-5 absolute; gradients as
gsplat's rasterizer tests (means2d 5e-3, conics 1e-3, features 1e-3, opacities 2e-3, rtol = atol).
"""
from __future__ import annotations

import logging
import sys
import threading
import types
from pathlib import Path

import pytest
import torch

from baselines.render import kernel, rasterize
from baselines.render.composite_reference import composite_reference
from baselines.render.projection import project_gaussians_torch
from baselines.render.tiles import bin_gaussians

VALUE_ATOL = 1e-5
GRAD_TOL = {"means2d": 5e-3, "conics": 1e-3, "opacities": 2e-3, "features": 1e-3}


# ---------------------------------------------------------------------------------------------
# Scene builders: each returns rasterize(**scene) keyword arguments (leaf tensors, no grad).


def _camera(width: int, height: int, focal: float, dtype: torch.dtype) -> dict:
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return {"viewmat": torch.eye(4, dtype=dtype), "K": K, "width": width, "height": height}


def random_scene(n: int, width: int, height: int, channels: int, seed: int = 0,
                 dtype: torch.dtype = torch.float32, pixels_wide: float = 2.0) -> dict:
    """N Gaussians in front of the camera, each about `pixels_wide` pixels (std) on screen."""
    g = torch.Generator().manual_seed(seed)
    focal = float(max(width, height))
    z = 2.0 + 4.0 * torch.rand(n, generator=g, dtype=dtype)
    x = (torch.rand(n, generator=g, dtype=dtype) - 0.5) * 1.2 * z * width / focal
    y = (torch.rand(n, generator=g, dtype=dtype) - 0.5) * 1.2 * z * height / focal
    scales = (0.3 + torch.rand(n, 3, generator=g, dtype=dtype)) * pixels_wide * z[:, None] / focal
    return {
        "means": torch.stack([x, y, z], dim=1),
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": scales,
        "opacities": 0.05 + 0.9 * torch.rand(n, generator=g, dtype=dtype),
        "features": torch.rand(n, channels, generator=g, dtype=dtype),
        **_camera(width, height, focal, dtype),
    }


def _with(scene: dict, **columns: torch.Tensor) -> dict:
    """Append Gaussians (given column by column) to a scene."""
    out = dict(scene)
    for key, extra in columns.items():
        out[key] = torch.cat([scene[key], extra.to(scene[key].dtype)])
    return out


def behind_and_near_plane_scene(seed: int = 1) -> dict:
    """Ordinary Gaussians plus ones behind the camera, at z = 0, and straddling the near plane."""
    base = random_scene(60, 40, 30, 3, seed)
    z = torch.tensor([-1.0, -0.005, 0.0, 0.008, 0.02, 0.05, 0.3])
    k = z.numel()
    return _with(
        base,
        means=torch.stack([torch.full((k,), 0.01), torch.full((k,), -0.01), z], dim=1),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(k, 1),
        scales=torch.full((k, 3), 0.1),
        opacities=torch.full((k,), 0.8),
        features=torch.rand(k, 3, generator=torch.Generator().manual_seed(seed)),
    )


def extreme_scales_scene(seed: int = 2) -> dict:
    """Ordinary Gaussians plus needles (1e-8) and giants (1e4) around the view."""
    base = random_scene(60, 40, 30, 3, seed)
    scales = torch.tensor([[1e-8] * 3, [1e-8, 1e-8, 1.0], [1e4] * 3, [1e4, 1e-8, 1e-8]])
    k = scales.shape[0]
    return _with(
        base,
        means=torch.tensor([[0.0, 0.0, 3.0], [0.1, 0.1, 4.0], [0.0, 0.0, 20.0], [0.0, 0.0, 5.0]]),
        quats=torch.randn(k, 4, generator=torch.Generator().manual_seed(seed)),
        scales=scales,
        opacities=torch.tensor([0.9, 0.5, 0.02, 0.3]),
        features=torch.rand(k, 3, generator=torch.Generator().manual_seed(seed)),
    )


def extreme_opacity_scene(seed: int = 3) -> dict:
    """Opacities exactly 0 and 1 (alpha clamped at 0.999 at the centre of the opaque ones)."""
    scene = random_scene(80, 40, 30, 3, seed, pixels_wide=3.0)
    scene["opacities"] = torch.where(torch.arange(80) % 2 == 0, torch.ones(80), torch.zeros(80))
    return scene


def stacked_scene(n: int = 1000, seed: int = 4) -> dict:
    """n Gaussians on one pixel at increasing depth (with depth ties): early termination."""
    g = torch.Generator().manual_seed(seed)
    width, height = 14, 11
    focal = 14.0
    depth = 2.0 + torch.arange(n, dtype=torch.float32).div(4).floor() * 0.01  # groups of 4 tie in depth
    offset = 0.02 * torch.randn(n, 2, generator=g)
    means = torch.cat([offset * depth[:, None] / focal, depth[:, None]], dim=1)
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": (0.5 + torch.rand(n, 3, generator=g)) * 5.0 * depth[:, None] / focal,
        "opacities": 0.2 + 0.6 * torch.rand(n, generator=g),
        "features": torch.rand(n, 3, generator=g),
        **_camera(width, height, focal, torch.float32),
    }


def offscreen_scene(seed: int = 5) -> dict:
    """Every Gaussian in front of the camera but outside the image."""
    scene = random_scene(50, 32, 24, 3, seed)
    scene["means"] = scene["means"] + torch.tensor([50.0, 0.0, 0.0])
    return scene


def empty_scene() -> dict:
    """N = 0."""
    scene = random_scene(1, 20, 12, 3)
    return {k: (v[:0] if isinstance(v, torch.Tensor) and k not in ("viewmat", "K") else v) for k, v in scene.items()}


HARD_CASES = {
    "behind_and_near_plane": behind_and_near_plane_scene,
    "extreme_scales": extreme_scales_scene,
    "extreme_opacity": extreme_opacity_scene,
    "stacked_1000": stacked_scene,
    "offscreen": offscreen_scene,
    "empty": empty_scene,
}


# ---------------------------------------------------------------------------------------------
# Helpers


@pytest.fixture(scope="module")
def compiled():
    """Skip when the kernel is switched off or there is no C++ compiler; a failing build fails."""
    ok, reason = kernel.kernel_available()
    if not ok and (kernel.disabled_by_env() or kernel.find_compiler() is None):
        pytest.skip(reason)
    assert ok, reason


def _leaves(scene: dict) -> dict:
    out = dict(scene)
    for key in ("means", "quats", "scales", "opacities", "features"):
        out[key] = scene[key].clone().requires_grad_(True)
    return out


def _upstream(image: torch.Tensor, alpha: torch.Tensor, seed: int = 7) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(image.shape, generator=g, dtype=image.dtype),
            torch.randn(alpha.shape, generator=g, dtype=alpha.dtype))


def _composite_with_grads(compositor, scene: dict, **kwargs) -> dict:
    """Project with torch, composite, backprop random upstream grads to the compositor inputs."""
    s = _leaves(scene)
    proj = project_gaussians_torch(s["means"], s["quats"], s["scales"], s["viewmat"], s["K"], s["width"],
                                   s["height"], s["opacities"])
    image, alpha = compositor(proj, s["opacities"], s["features"], s["width"], s["height"], **kwargs)
    gi, ga = _upstream(image, alpha)
    inputs = {"means2d": proj.means2d, "conics": proj.conics, "opacities": s["opacities"], "features": s["features"]}
    grads = torch.autograd.grad((image * gi).sum() + (alpha * ga).sum(), list(inputs.values()), allow_unused=True)
    out = {"image": image.detach(), "alpha": alpha.detach()}
    out.update({k: (g if g is not None else torch.zeros_like(v)) for (k, v), g in zip(inputs.items(), grads)})
    return out


def _assert_matches(got: dict, want: dict, value_atol: float = VALUE_ATOL, grad_tol: dict | None = None) -> None:
    grad_tol = GRAD_TOL if grad_tol is None else grad_tol
    for key in ("image", "alpha"):
        torch.testing.assert_close(got[key], want[key], atol=value_atol, rtol=0, msg=lambda m: f"{key}: {m}")
    for key, tol in grad_tol.items():
        assert torch.isfinite(got[key]).all(), f"{key} gradient is not finite"
        torch.testing.assert_close(got[key], want[key], atol=tol, rtol=tol, msg=lambda m: f"grad {key}: {m}")


def _rasterize_with_grads(scene: dict, backend: str) -> dict:
    s = _leaves(scene)
    feats, depth, alpha, meta = rasterize(**s, backend=backend)
    g = torch.Generator().manual_seed(11)
    loss = sum((t * torch.randn(t.shape, generator=g)).sum() for t in (feats, depth, alpha))
    params = ("means", "quats", "scales", "opacities", "features")
    if loss.requires_grad:
        loss.backward()
    out = {"features_img": feats.detach(), "depth": depth.detach(), "alpha": alpha.detach()}
    for p in params:
        out[p] = s[p].grad if s[p].grad is not None else torch.zeros_like(s[p])
    out["means2d"] = meta.means2d.grad if meta.means2d.grad is not None else torch.zeros_like(meta.means2d)
    out["backend"] = meta.backend
    return out


def _assert_close_scaled(got: torch.Tensor, want: torch.Tensor, tol: float, name: str) -> None:
    """rtol = tol and atol = tol x the largest magnitude (gradients w.r.t. 3D parameters span decades)."""
    scale = max(1.0, float(want.abs().max())) if want.numel() else 1.0
    torch.testing.assert_close(got, want, rtol=tol, atol=tol * scale, msg=lambda m: f"{name}: {m}")


# ---------------------------------------------------------------------------------------------
# Values and gradients against the dense reference


@pytest.mark.parametrize(
    "n, width, height, channels",
    [(40, 37, 29, 1), (300, 64, 48, 3), (500, 100, 70, 10), (120, 16, 16, 3), (200, 50, 81, 3)],
)
def test_composite_matches_reference(compiled, n, width, height, channels):
    scene = random_scene(n, width, height, channels, seed=n)
    got = _composite_with_grads(kernel.composite_kernel, scene)
    want = _composite_with_grads(composite_reference, scene)
    assert want["alpha"].max() > 0.5  # the scene does cover the image
    _assert_matches(got, want)


def test_float64_matches_reference_tightly(compiled):
    scene = random_scene(150, 45, 33, 3, seed=3, dtype=torch.float64)
    got = _composite_with_grads(kernel.composite_kernel, scene)
    want = _composite_with_grads(composite_reference, scene)
    _assert_matches(got, want, value_atol=1e-12, grad_tol={k: 1e-9 for k in GRAD_TOL})


def test_rasterize_cpu_backend_matches_reference(compiled):
    scene = random_scene(400, 72, 56, 3, seed=21)
    got = _rasterize_with_grads(scene, "cpu")
    want = _rasterize_with_grads(scene, "reference")
    assert got["backend"] == "cpu"
    for key in ("features_img", "alpha"):
        torch.testing.assert_close(got[key], want[key], atol=VALUE_ATOL, rtol=0)
    torch.testing.assert_close(got["depth"], want["depth"], atol=VALUE_ATOL, rtol=1e-5)
    assert got["means2d"].abs().max() > 0  # densification reads meta.means2d.grad
    _assert_close_scaled(got["means2d"], want["means2d"], GRAD_TOL["means2d"], "means2d")
    _assert_close_scaled(got["opacities"], want["opacities"], GRAD_TOL["opacities"], "opacities")
    _assert_close_scaled(got["features"], want["features"], GRAD_TOL["features"], "features")
    for key in ("means", "quats", "scales"):
        assert got[key].abs().max() > 0, key
        _assert_close_scaled(got[key], want[key], 5e-3, key)


@pytest.mark.parametrize("case", list(HARD_CASES))
def test_hard_cases_finite_and_match_reference(compiled, case):
    scene = HARD_CASES[case]()
    got = _rasterize_with_grads(scene, "cpu")
    want = _rasterize_with_grads(scene, "reference")
    for key, value in got.items():
        if isinstance(value, torch.Tensor):
            assert torch.isfinite(value).all(), f"{case}: {key} not finite"
    for key in ("features_img", "alpha"):
        torch.testing.assert_close(got[key], want[key], atol=VALUE_ATOL, rtol=0)
    torch.testing.assert_close(got["depth"], want["depth"], atol=VALUE_ATOL, rtol=1e-5)
    for key in ("means2d", "opacities", "features", "means", "quats", "scales"):
        _assert_close_scaled(got[key], want[key], GRAD_TOL.get(key, 5e-3), f"{case}: {key}")


def test_stacked_gaussians_terminate_early_like_reference(compiled):
    scene = stacked_scene()
    got = _composite_with_grads(kernel.composite_kernel, scene)
    want = _composite_with_grads(composite_reference, scene)
    _assert_matches(got, want)
    # Termination did happen: the centre pixels are saturated, and the Gaussians behind the stop
    # (most of the 1000) receive exactly zero gradient in both implementations.
    assert float(want["alpha"].max()) > 1 - 2e-4
    untouched_ref = (want["features"] == 0).all(dim=1)
    untouched_ker = (got["features"] == 0).all(dim=1)
    assert untouched_ref.sum() > 900
    assert torch.equal(untouched_ker, untouched_ref)


def test_depth_ties_keep_index_order(compiled):
    # Two coincident Gaussians at equal depth with different colours: the lower index is in front.
    scene = random_scene(2, 16, 16, 3, seed=0, pixels_wide=3.0)
    scene["means"] = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0]])
    scene["opacities"] = torch.tensor([0.9, 0.9])
    scene["features"] = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    got = _composite_with_grads(kernel.composite_kernel, scene)
    want = _composite_with_grads(composite_reference, scene)
    _assert_matches(got, want)
    centre = got["image"][8, 8]
    assert centre[0] > centre[1] * 5


# ---------------------------------------------------------------------------------------------
# Binning and determinism


@pytest.mark.parametrize("case", ["random", "behind_and_near_plane", "extreme_scales", "stacked_1000", "empty"])
def test_compiled_binning_equals_torch_binning(compiled, case):
    scene = random_scene(2000, 150, 97, 1, seed=9) if case == "random" else HARD_CASES[case]()
    proj = project_gaussians_torch(scene["means"], scene["quats"], scene["scales"], scene["viewmat"], scene["K"],
                                   scene["width"], scene["height"], scene["opacities"])
    want = bin_gaussians(proj, scene["width"], scene["height"])
    got = kernel.bin_gaussians_compiled(proj, scene["width"], scene["height"])
    assert (got.tiles_x, got.tiles_y) == (want.tiles_x, want.tiles_y)
    assert torch.equal(got.offsets, want.offsets)
    assert torch.equal(got.gaussian_ids, want.gaussian_ids)


def test_bitwise_identical_across_thread_counts(compiled):
    scene = random_scene(4000, 120, 90, 4, seed=5, pixels_wide=4.0)
    runs = [_composite_with_grads(kernel.composite_kernel, scene, num_threads=t) for t in (1, 2, 3, 2)]
    for run in runs[1:]:
        for key, value in runs[0].items():
            assert torch.equal(value, run[key]), f"{key} differs between thread counts"


# ---------------------------------------------------------------------------------------------
# Fallback to the torch tiled path, build and cache


def _fake_tiled_module(calls: list) -> types.ModuleType:
    module = types.ModuleType("baselines.render.composite_tiled")

    def composite_tiled(projection, opacities, features, width, height):
        calls.append(features.shape)
        return composite_reference(projection, opacities, features, width, height)

    module.composite_tiled = composite_tiled
    return module


def test_cpu_backend_uses_the_kernel_when_available(compiled, monkeypatch):
    broken = types.ModuleType("baselines.render.composite_tiled")

    def composite_tiled(*args, **kwargs):
        raise AssertionError("the cpu backend fell back although the kernel is available")

    broken.composite_tiled = composite_tiled
    monkeypatch.setitem(sys.modules, "baselines.render.composite_tiled", broken)
    monkeypatch.delenv(kernel.ENV_SWITCH, raising=False)
    feats, _, alpha, meta = rasterize(**random_scene(50, 30, 20, 3), backend="cpu")
    assert meta.backend == "cpu" and alpha.max() > 0


def test_env_var_forces_torch_path_and_logs_once(monkeypatch, caplog):
    calls: list = []
    monkeypatch.setitem(sys.modules, "baselines.render.composite_tiled", _fake_tiled_module(calls))
    monkeypatch.setenv(kernel.ENV_SWITCH, "0")
    monkeypatch.setattr(kernel, "_logged_reasons", set())

    def must_not_run(*args, **kwargs):
        raise AssertionError("the compiled kernel ran although it is disabled")

    monkeypatch.setattr(kernel, "composite_kernel", must_not_run)
    assert kernel.kernel_available() == (False, kernel.disabled_by_env())
    scene = random_scene(100, 40, 30, 3, seed=2)
    with caplog.at_level(logging.INFO, logger=kernel.__name__):
        first = rasterize(**scene, backend="cpu")
        second = rasterize(**scene, backend="cpu")
    want = rasterize(**scene, backend="reference")
    assert len(calls) == 2
    for got in (first, second):
        for g, w in zip(got[:3], want[:3]):
            torch.testing.assert_close(g, w, atol=VALUE_ATOL, rtol=1e-5)
    messages = [r.getMessage() for r in caplog.records if r.name == kernel.__name__]
    assert len(messages) == 1 and kernel.ENV_SWITCH in messages[0]


def test_torch_tiled_fallback_matches_kernel(compiled, monkeypatch):
    pytest.importorskip("baselines.render.composite_tiled")
    scene = random_scene(300, 50, 40, 3, seed=8)
    with_kernel = _rasterize_with_grads(scene, "cpu")
    monkeypatch.setenv(kernel.ENV_SWITCH, "0")
    without = _rasterize_with_grads(scene, "cpu")
    for key in ("features_img", "depth", "alpha"):
        torch.testing.assert_close(with_kernel[key], without[key], atol=VALUE_ATOL, rtol=1e-5)
    for key in ("means2d", "opacities", "features", "means", "quats", "scales"):
        _assert_close_scaled(with_kernel[key], without[key], GRAD_TOL.get(key, 5e-3), key)


@pytest.fixture
def fresh_kernel_state(monkeypatch, tmp_path):
    """Forget the loaded library and point the cache at an empty directory."""
    monkeypatch.setattr(kernel, "_library", None)
    monkeypatch.setattr(kernel, "_load_error", None)
    monkeypatch.setenv(kernel.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.delenv(kernel.ENV_SWITCH, raising=False)
    return tmp_path / "cache"


def test_missing_compiler_is_reported(fresh_kernel_state, monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler-reflow4dgs")
    ok, reason = kernel.kernel_available()
    assert not ok and "no C++ compiler" in reason and "no-such-compiler-reflow4dgs" in reason
    assert kernel.unusable_reason(torch.zeros(1, 3)) == reason


def test_failing_build_is_reported_and_attempted_once(fresh_kernel_state, monkeypatch, tmp_path):
    fake = tmp_path / "broken-c++"
    fake.write_text("#!/bin/sh\necho 'fatal: simulated compiler failure' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CXX", str(fake))
    ok, reason = kernel.kernel_available()
    assert not ok and "simulated compiler failure" in reason
    fake.unlink()  # a second call must reuse the recorded failure, not run the compiler again
    assert kernel.kernel_available() == (False, reason)
    assert not any(fresh_kernel_state.glob("*.so")) and not any(fresh_kernel_state.glob(".build-*"))


def test_concurrent_builds_leave_one_valid_library(fresh_kernel_state, monkeypatch):
    # Two builders racing on the same cache entry (as two processes on first use would): each
    # compiles in its own temporary directory and renames atomically, so the survivor is whole.
    compiler = kernel.find_compiler()
    if compiler is None:
        pytest.skip("no C++ compiler")
    target = kernel.library_path(compiler)
    errors: list = []

    def build():
        try:
            kernel._build(compiler, target)
        except Exception as exc:  # reported below
            errors.append(exc)

    workers = [threading.Thread(target=build) for _ in range(2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    assert not errors
    assert list(fresh_kernel_state.iterdir()) == [target]  # no temporary leftovers

    def no_build(*args):
        raise AssertionError("rebuilt although the cache holds the library")

    monkeypatch.setattr(kernel, "_build", no_build)  # a fresh load must use the cached file as is
    ok, path = kernel.kernel_available()
    assert ok and Path(path) == target


def test_unsupported_dtype_falls_back():
    assert "float16" in kernel.unusable_reason(torch.zeros(2, 3, dtype=torch.float16))


def test_kernel_rejects_mixed_dtypes(compiled):
    scene = random_scene(10, 16, 16, 3)
    proj = project_gaussians_torch(scene["means"], scene["quats"], scene["scales"], scene["viewmat"], scene["K"],
                                   16, 16, scene["opacities"])
    with pytest.raises(ValueError, match="features"):
        kernel.composite_kernel(proj, scene["opacities"], scene["features"].double(), 16, 16)
