"""Compiled CPU projection (baselines/render/project_kernel.py) against its torch twin.

project_gaussians_torch is the oracle (itself tested against the pinhole model, Monte Carlo
covariances and gsplat in test_raster_projection.py). Covered: values, radii, visibility and the
gradients of means, quats and scales for posed random scenes (float32 and float64) and every hard
case of raster_cases (behind the camera, on and across the near plane, at the camera centre, tiny
and huge scales, zero quaternions, the FOV clamp); gradcheck in float64; thread-count
independence; that the cpu backend uses it; and the fallbacks (switches, camera gradients).
"""
from __future__ import annotations

import logging

import pytest
import torch

from baselines import native_build
from baselines.render import project_kernel
from baselines.render.backends import resolve_backend
from baselines.render.projection import project_gaussians_torch
from raster_cases import HARD_CASES, random_scene

DIFFERENTIABLE = ("means2d", "cov2d", "conics", "depths")


@pytest.fixture(scope="module")
def compiled():
    ok, reason = project_kernel.LIBRARY.available()
    if not ok and native_build.find_compiler() is None:
        pytest.skip(reason)
    assert ok, reason  # a compiler is present: the kernel must build
    return ok


def _run(fn, scene, seed=0, **kwargs):
    """Projection of the scene and the gradients of a random weighting of its differentiable outputs."""
    inputs = [t.detach().clone().requires_grad_() for t in (scene.means, scene.quats, scene.scales)]
    proj = fn(*inputs, scene.viewmat, scene.K, scene.width, scene.height, scene.opacities, **kwargs)
    g = torch.Generator().manual_seed(seed)
    loss = sum((proj[k] * torch.randn(proj[k].shape, generator=g, dtype=proj[k].dtype)).sum() for k in DIFFERENTIABLE)
    grads = torch.autograd.grad(loss, inputs, allow_unused=True)
    return proj, [torch.zeros_like(x) if gr is None else gr for x, gr in zip(inputs, grads)]


def _assert_same(scene, value_tol, grad_tol):
    want, want_grads = _run(project_gaussians_torch, scene)
    got, got_grads = _run(project_kernel.project_gaussians_kernel, scene)
    for key in DIFFERENTIABLE:
        torch.testing.assert_close(got[key], want[key], **value_tol, msg=lambda m, key=key: f"{key}: {m}")
    assert torch.equal(got.visible, want.visible)
    assert torch.equal(got.radii, want.radii)
    # relative to the largest gradient entry of any input: sums of products in another order (a
    # gradient that is zero in exact arithmetic, as the quaternion's of an isotropic Gaussian, is
    # rounding noise in both)
    scale = max([float(w.abs().max()) for w in want_grads if w.numel()] + [1e-30])
    for name, g, w in zip(("means", "quats", "scales"), got_grads, want_grads):
        assert torch.isfinite(g).all(), name
        torch.testing.assert_close(g / scale, w / scale, **grad_tol, msg=lambda m, name=name: f"{name} gradient: {m}")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_kernel_equals_torch_twin_on_posed_scenes(compiled, dtype, seed):
    scene = random_scene(3000, 96, 64, seed=seed, margin=0.6, pixel_sigma=(0.2, 40.0), dtype=dtype)
    scene.quats[:5] = 0.0  # zero quaternions: identity rotation, no gradient
    if dtype == torch.float32:
        # b = t0.t1 and det cancel: a few ulps of the terms apart (measured up to 1.4e-5 relative)
        _assert_same(scene, {"rtol": 5e-5, "atol": 1e-5}, {"rtol": 5e-5, "atol": 1e-5})
    else:
        _assert_same(scene, {"rtol": 1e-11, "atol": 1e-11}, {"rtol": 1e-10, "atol": 1e-10})


@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_kernel_equals_torch_twin_on_hard_cases(compiled, name):
    scene = HARD_CASES[name].scene.to(torch.float64)
    _assert_same(scene, {"rtol": 1e-11, "atol": 1e-9}, {"rtol": 1e-9, "atol": 1e-9})
    # float32 too: every value and gradient finite where the twin's are
    proj, grads = _run(project_kernel.project_gaussians_kernel, HARD_CASES[name].scene.to(torch.float32))
    for key in DIFFERENTIABLE:
        assert torch.isfinite(proj[key]).all(), key
    assert all(torch.isfinite(g).all() for g in grads)


def test_a_blown_up_gaussian_in_float32_gets_the_twins_finite_gradients(compiled):
    """A dynamic Gaussian of a real DAVIS run (libby, fine iteration 817) whose deformed scales had
    grown to ~1e12: |t0 x t1|^2 overflows float32 (det = inf, conic 0, no gradient through det),
    and forming t1 x k before scaling it by that zero gradient made NaN means gradients that
    stopped the run. The kernel must give the torch twin's finite gradients, with and without
    gradient on the blown-up Gaussian's own outputs."""
    n = 3
    means = torch.tensor([[-3.876, 14.81, 20.73], [0.1, -0.2, 3.0], [0.4, 0.1, 4.0]])
    quats = torch.tensor([[-0.6657, 0.0203, -0.7115, 0.2241], [1.0, 0.0, 0.0, 0.0], [0.9, 0.1, 0.3, 0.0]])
    scales = torch.tensor([[5.04e10, 3.89e12, 8.63e9], [0.05, 0.02, 0.03], [0.1, 0.1, 0.02]])
    viewmat, K = torch.eye(4), torch.tensor([[282.4, 0.0, 160.0], [0.0, 282.4, 90.0], [0.0, 0.0, 1.0]])
    for own_gradient in (False, True):
        results = []
        for fn in (project_gaussians_torch, project_kernel.project_gaussians_kernel):
            inputs = [t.clone().requires_grad_() for t in (means, quats, scales)]
            proj = fn(*inputs, viewmat, K, 320, 180, torch.full((n,), 0.9))
            weight = torch.ones(n, 1) if own_gradient else torch.tensor([[0.0], [1.0], [1.0]])
            loss = sum((proj[k].reshape(n, -1) * weight).sum() for k in DIFFERENTIABLE)
            results.append((proj, torch.autograd.grad(loss, inputs)))
        (want, want_grads), (got, got_grads) = results
        assert not torch.isfinite(torch.linalg.det(want.cov2d[0].double()).float())  # the overflow is real
        assert torch.equal(got.visible, want.visible)
        for name, g, w in zip(("means", "quats", "scales"), got_grads, want_grads):
            assert torch.isfinite(w).all() and torch.isfinite(g).all(), (name, own_gradient, g)
            torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-6, msg=lambda m, name=name: f"{name}: {m}")


def test_kernel_passes_gradcheck(compiled):
    scene = random_scene(12, 40, 30, seed=3, margin=0.4, dtype=torch.float64)
    scene.means[0] = scene.means[0] * 0  # one Gaussian behind or beside the camera
    inputs = tuple(t.detach().clone().requires_grad_() for t in (scene.means, scene.quats, scene.scales))

    def project(means, quats, scales):
        proj = project_kernel.project_gaussians_kernel(means, quats, scales, scene.viewmat, scene.K, scene.width,
                                                       scene.height, scene.opacities)
        return tuple(proj[k] for k in DIFFERENTIABLE)

    assert torch.autograd.gradcheck(project, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_results_do_not_depend_on_the_thread_count(compiled):
    scene = random_scene(9000, 64, 48, seed=4)  # several blocks of 4096 Gaussians
    runs = [_run(project_kernel.project_gaussians_kernel, scene, num_threads=threads) for threads in (1, 3)]
    (p1, g1), (p3, g3) = runs
    for key in p1.keys():
        assert torch.equal(p1[key], p3[key]), key
    assert all(torch.equal(a, b) for a, b in zip(g1, g3))


def test_cpu_backend_projects_with_the_kernel(compiled, monkeypatch):
    scene = random_scene(50, 32, 24, seed=5)
    means = scene.means.clone().requires_grad_()
    monkeypatch.setenv(project_kernel.ENV_SWITCH, "1")
    proj = resolve_backend("cpu", means.device).project(means, scene.quats, scene.scales, scene.viewmat, scene.K,
                                                        scene.width, scene.height, scene.opacities, 0.01, 1e10, 0.3)
    assert type(proj.means2d.grad_fn).__name__ == "_ProjectKernelBackward"


def test_switches_and_camera_gradients_take_the_torch_path(monkeypatch, caplog):
    scene = random_scene(50, 32, 24, seed=6)
    cpu = resolve_backend("cpu", scene.means.device)

    def grad_fn_name(viewmat):
        means = scene.means.clone().requires_grad_()
        proj = cpu.project(means, scene.quats, scene.scales, viewmat, scene.K, scene.width, scene.height,
                           scene.opacities, 0.01, 1e10, 0.3)
        return type(proj.means2d.grad_fn).__name__

    monkeypatch.setattr(project_kernel, "_logged_reasons", set())
    with caplog.at_level(logging.INFO, logger=project_kernel.__name__):
        for name, value in ((project_kernel.ENV_SWITCH, "0"), (project_kernel.ENV_ALL_KERNELS, "off")):
            monkeypatch.setenv(name, value)
            assert grad_fn_name(scene.viewmat) != "_ProjectKernelBackward"
            assert grad_fn_name(scene.viewmat) != "_ProjectKernelBackward"  # logged once per reason
            monkeypatch.delenv(name)
    assert len([r for r in caplog.records if r.name == project_kernel.__name__]) == 2
    # A camera that needs gradients: the torch twin differentiates it
    viewmat = scene.viewmat.clone().requires_grad_()
    assert project_kernel.unusable_reason(scene.means, viewmat, scene.K) is not None
    assert grad_fn_name(viewmat) != "_ProjectKernelBackward"


def test_missing_compiler_falls_back_to_the_torch_twin(monkeypatch, tmp_path, caplog):
    monkeypatch.setenv(native_build.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.setenv("CXX", "no-such-compiler-reflow4dgs")
    monkeypatch.setattr(project_kernel, "_logged_reasons", set())
    project_kernel.LIBRARY.reset()
    try:
        scene = random_scene(20, 32, 24, seed=7)
        with caplog.at_level(logging.INFO, logger=project_kernel.__name__):
            proj = resolve_backend("cpu", scene.means.device).project(
                scene.means, scene.quats, scene.scales, scene.viewmat, scene.K, scene.width, scene.height,
                scene.opacities, 0.01, 1e10, 0.3)
        want = project_gaussians_torch(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K, scene.width,
                                       scene.height, scene.opacities)
        assert torch.equal(proj.means2d, want.means2d)
        records = [r for r in caplog.records if r.name == project_kernel.__name__]
        assert len(records) == 1 and records[0].levelno == logging.WARNING
        assert "no C++ compiler" in records[0].getMessage()
    finally:
        project_kernel.LIBRARY.reset()
