"""The cpu backend's compositors and the public cpu backend against the dense reference."""
from __future__ import annotations

import functools

import pytest
import torch

from baselines.render import composite_tiled as tiled_module
from baselines.render import kernel as kernel_module
from baselines.render import rasterize
from baselines.render.composite_reference import composite_reference
from baselines.render.composite_tiled import composite_tiled
from raster_cases import (
    CPU_COMPOSITORS, GRAD_KEYS, RANDOM_SCENES, VALUE_ATOL, assert_grads_close, assert_matches, composite_grads,
    named_scene, over_cpu_compositors, project, random_scene, reference_grads, requires_kernel, weighted_loss,
)


@over_cpu_compositors
@pytest.mark.parametrize("scene_name", RANDOM_SCENES.keys())
def test_cpu_compositor_matches_reference(compositor, scene_name):
    expected = reference_grads(scene_name)
    assert expected["alpha"].max() > 0.95  # the scene has opaque regions
    assert_matches(composite_grads(compositor, named_scene(scene_name)), expected)


@over_cpu_compositors
def test_float64_matches_reference_to_rounding(compositor):
    # Same decisions and float64 arithmetic: only the summation order differs (~1e-16 relative).
    scene = random_scene(150, 45, 33, channels=3, seed=3, dtype=torch.float64)
    got = composite_grads(compositor, scene)
    want = composite_grads(composite_reference, scene)
    for key, value in want.items():
        scale = max(1.0, float(value.abs().max())) if value.numel() else 1.0
        torch.testing.assert_close(got[key], value, rtol=1e-9, atol=1e-12 * scale, msg=lambda m: f"{key}: {m}")


def _spy_on_cpu_paths(monkeypatch) -> list[str]:
    """Record which compositor the cpu backend calls (it looks both up at call time)."""
    ran: list[str] = []
    for module, name in ((kernel_module, "composite_kernel"), (tiled_module, "composite_tiled")):
        def spy(*args, _original=getattr(module, name), _name=name, **kwargs):
            ran.append(_name)
            return _original(*args, **kwargs)

        monkeypatch.setattr(module, name, spy)
    return ran


@pytest.mark.parametrize("switch, path", [pytest.param("0", "composite_tiled", id="torch_tiled"),
                                          pytest.param("1", "composite_kernel", id="kernel", marks=requires_kernel)])
def test_public_rasterize_cpu_matches_reference(monkeypatch, switch, path):
    # Both paths of the cpu backend (the kernel, and the torch tiled fallback the environment
    # switch selects) end to end: background, depth, meta, gradients down to the 3D parameters.
    monkeypatch.setenv(kernel_module.ENV_SWITCH, switch)
    scene = random_scene(300, 50, 42, channels=4, seed=4)
    background = torch.tensor([0.3, 0.1, 0.9, 0.5])
    ran = _spy_on_cpu_paths(monkeypatch)
    results = {}
    for backend in ("reference", "cpu"):
        s = scene.to(torch.float32).requires_grad_()
        image, depth, alpha, meta = rasterize(*s.args(), backend=backend, background=background)
        assert meta.backend == backend and (meta.width, meta.height) == (50, 42)
        weighted_loss((image, depth, alpha), seed=7).backward()
        results[backend] = dict(image=image.detach(), depth=depth.detach(), alpha=alpha.detach(),
                                means2d=meta.means2d.grad, **{k: v.grad for k, v in s.gaussian_tensors.items()})
    assert ran == [path]
    ref, cpu = results["reference"], results["cpu"]
    for key in ("image", "alpha"):
        torch.testing.assert_close(cpu[key], ref[key], atol=VALUE_ATOL, rtol=0)
    # Depth = sum(w z) / alpha: relative to the scene depth (z in [2, 8]).
    torch.testing.assert_close(cpu["depth"], ref["depth"], atol=VALUE_ATOL * 8, rtol=1e-5)
    for key in GRAD_KEYS:
        if key == "conics":
            continue  # internal to the projection here; covered by the compositor tests
        assert ref[key].abs().max() > 0, key  # every gradient is exercised (densification reads means2d)
        assert_grads_close(cpu[key], ref[key], key)


@pytest.mark.parametrize("case_name", ["stack_1000", "huge_scale"])
def test_torch_tiled_batches_and_segments_match_reference(case_name):
    # Tiny segments and batches force many batches, many segments, the float64 transmittance
    # carry across segments and tiles leaving early (stack_1000 stops after a few dozen entries).
    small_steps = functools.partial(composite_tiled, max_pairs=256 * 64 * 2, segment=64)
    assert_matches(composite_grads(small_steps, named_scene(case_name)), reference_grads(case_name))


def test_torch_tiled_random_scene_with_small_steps():
    small_steps = functools.partial(composite_tiled, max_pairs=256 * 8 * 3, segment=8)
    assert_matches(composite_grads(small_steps, named_scene("400g_70x50_c3")), reference_grads("400g_70x50_c3"))


@over_cpu_compositors
def test_forward_without_grad_matches(compositor):
    scene = named_scene("120g_45x37_c1").requires_grad_()
    expected = reference_grads("120g_45x37_c1")
    with torch.no_grad():
        image, alpha = compositor(project(scene), scene.opacities, scene.features, scene.width, scene.height)
    assert not image.requires_grad and not alpha.requires_grad
    torch.testing.assert_close(image, expected["image"], atol=VALUE_ATOL, rtol=0)
    torch.testing.assert_close(alpha, expected["alpha"], atol=VALUE_ATOL, rtol=0)


def _tiny_scene_float64():
    scene = random_scene(4, 11, 9, channels=2, seed=11, pixel_sigma=(1.0, 2.5), depth=(2.0, 3.0), margin=0.0)
    return scene.to(torch.float64)


def test_reference_gradcheck_float64():
    scene = _tiny_scene_float64()

    def render(means, quats, scales, opacities, features):
        image, depth, alpha, _ = rasterize(means, quats, scales, opacities, features, scene.viewmat, scene.K,
                                           scene.width, scene.height, backend="reference")
        return image, depth, alpha

    inputs = tuple(t.detach().clone().requires_grad_() for t in scene.gaussian_tensors.values())
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


@pytest.mark.parametrize("compositor", [
    *CPU_COMPOSITORS, pytest.param(functools.partial(composite_tiled, segment=1), id="torch_tiled_segment_1")])
def test_cpu_compositor_backward_gradcheck_float64(compositor):
    # The hand-written backward passes against finite differences, through the stage inputs.
    scene = _tiny_scene_float64()
    proj = project(scene)

    def render(means2d, conics, opacities, features):
        proj.means2d, proj.conics = means2d, conics
        return compositor(proj, opacities, features, scene.width, scene.height)

    inputs = tuple(t.detach().clone().requires_grad_()
                   for t in (proj.means2d, proj.conics, scene.opacities, scene.features))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
