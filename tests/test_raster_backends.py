"""The cpu backend against the dense reference: values and gradients on random scenes."""
from __future__ import annotations

import pytest
import torch

from baselines.render import rasterize
from baselines.render.composite_reference import composite_reference
from baselines.render.composite_tiled import composite_tiled
from raster_cases import (
    CPU_COMPOSITORS, HARD_CASES, assert_grads_close, composite_grads, project, random_scene, weighted_loss,
)

VALUE_ATOL = 1e-5
GRAD_KEYS = ("means", "quats", "scales", "opacities", "features", "means2d")
# Image sizes not divisible by 16 (partial border tiles), C = 1, 3 and 10, plus a deep scene of
# opaque Gaussians where most pixels reach the transmittance stop.
SCENES = {
    "120g_45x37_c1": dict(n=120, width=45, height=37, channels=1, seed=0, pixel_sigma=(0.5, 3.0)),
    "400g_70x50_c3": dict(n=400, width=70, height=50, channels=3, seed=1, pixel_sigma=(0.5, 3.0)),
    "250g_33x61_c10": dict(n=250, width=33, height=61, channels=10, seed=2, pixel_sigma=(0.5, 3.0)),
    "deep_500g_40x23_c3": dict(n=500, width=40, height=23, channels=3, seed=3, opacity=(0.5, 0.99),
                               pixel_sigma=(1.0, 4.0)),
}
_reference_cache: dict[str, dict] = {}


def _reference(name: str) -> dict:
    if name not in _reference_cache:
        _reference_cache[name] = composite_grads(composite_reference, random_scene(**SCENES[name]))
    return _reference_cache[name]


def _assert_matches(result: dict, expected: dict) -> None:
    torch.testing.assert_close(result["image"], expected["image"], atol=VALUE_ATOL, rtol=0)
    torch.testing.assert_close(result["alpha"], expected["alpha"], atol=VALUE_ATOL, rtol=0)
    for key in GRAD_KEYS:
        assert_grads_close(result[key], expected[key], key)


@pytest.mark.parametrize("compositor", CPU_COMPOSITORS.values(), ids=CPU_COMPOSITORS.keys())
@pytest.mark.parametrize("scene_name", SCENES.keys())
def test_cpu_compositor_matches_reference(compositor, scene_name):
    expected = _reference(scene_name)
    assert expected["alpha"].max() > 0.95  # the scene has opaque regions
    _assert_matches(composite_grads(compositor, random_scene(**SCENES[scene_name])), expected)


def test_public_rasterize_cpu_matches_reference():
    scene = random_scene(300, 50, 42, channels=4, seed=4)
    background = torch.tensor([0.3, 0.1, 0.9, 0.5])
    results = {}
    for backend in ("reference", "cpu"):
        s = scene.to(torch.float32).requires_grad_()
        image, depth, alpha, meta = rasterize(*s.args(), backend=backend, background=background)
        assert meta.backend == backend and (meta.width, meta.height) == (50, 42)
        weighted_loss((image, depth, alpha), seed=7).backward()
        results[backend] = dict(image=image.detach(), depth=depth.detach(), alpha=alpha.detach(),
                                means2d=meta.means2d.grad, **{k: v.grad for k, v in s.gaussian_tensors.items()})
    ref, cpu = results["reference"], results["cpu"]
    for key in ("image", "alpha"):
        torch.testing.assert_close(cpu[key], ref[key], atol=VALUE_ATOL, rtol=0)
    # Depth = sum(w z) / alpha: relative to the scene depth (z in [2, 8]).
    torch.testing.assert_close(cpu["depth"], ref["depth"], atol=VALUE_ATOL * 8, rtol=1e-5)
    for key in GRAD_KEYS:
        assert_grads_close(cpu[key], ref[key], key)


@pytest.mark.parametrize("case_name", ["stack_1000", "huge_scale"])
def test_torch_tiled_batches_and_segments_match_reference(case_name):
    # Tiny segments and batches force many batches, many segments, the float64 transmittance
    # carry across segments and tiles leaving early (stack_1000 stops after a few dozen entries).
    scene = HARD_CASES[case_name].scene
    expected = composite_grads(composite_reference, scene)

    def small_steps(*args):
        return composite_tiled(*args, max_pairs=256 * 64 * 2, segment=64)

    _assert_matches(composite_grads(small_steps, scene), expected)


def test_torch_tiled_random_scene_with_small_steps():
    scene = random_scene(**SCENES["400g_70x50_c3"])

    def small_steps(*args):
        return composite_tiled(*args, max_pairs=256 * 8 * 3, segment=8)

    _assert_matches(composite_grads(small_steps, scene), _reference("400g_70x50_c3"))


def test_forward_without_grad_matches():
    scene = random_scene(**SCENES["120g_45x37_c1"]).requires_grad_()
    with torch.no_grad():
        proj = project(scene)
        for compositor in CPU_COMPOSITORS.values():
            image, alpha = compositor(proj, scene.opacities, scene.features, scene.width, scene.height)
            torch.testing.assert_close(image, _reference("120g_45x37_c1")["image"], atol=VALUE_ATOL, rtol=0)
            torch.testing.assert_close(alpha, _reference("120g_45x37_c1")["alpha"], atol=VALUE_ATOL, rtol=0)


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


@pytest.mark.parametrize("segment", [32, 1])
def test_torch_tiled_backward_gradcheck_float64(segment):
    # The hand-written backward against finite differences, through the stage inputs.
    scene = _tiny_scene_float64()
    proj = project(scene)

    def render(means2d, conics, opacities, features):
        proj.means2d, proj.conics = means2d, conics
        return composite_tiled(proj, opacities, features, scene.width, scene.height, segment=segment)

    inputs = tuple(t.detach().clone().requires_grad_()
                   for t in (proj.means2d, proj.conics, scene.opacities, scene.features))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
