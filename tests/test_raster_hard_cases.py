"""Degenerate and extreme scenes: finite outputs and finite gradients w.r.t. every input."""
from __future__ import annotations

import pytest
import torch

from baselines.render import rasterize
from raster_cases import (
    ALL_COMPOSITORS, CPU_COMPOSITORS, HARD_CASES, assert_grads_close, composite_grads, project, weighted_loss,
)

CASES = pytest.mark.parametrize("case_name", HARD_CASES.keys())
INPUTS = ("means", "quats", "scales", "opacities", "features")
_reference_cache: dict[str, dict] = {}


def _reference(case_name: str) -> dict:
    if case_name not in _reference_cache:
        _reference_cache[case_name] = composite_grads(ALL_COMPOSITORS["reference"], HARD_CASES[case_name].scene)
    return _reference_cache[case_name]


def _assert_finite(result: dict, keys) -> None:
    for key in keys:
        assert result[key] is not None, f"no gradient reached {key}"
        assert torch.isfinite(result[key]).all(), f"{key} is not finite"


@CASES
def test_reference_is_finite(case_name):
    _assert_finite(_reference(case_name), ("image", "alpha", "means2d") + INPUTS)


@CASES
@pytest.mark.parametrize("compositor", CPU_COMPOSITORS.values(), ids=CPU_COMPOSITORS.keys())
def test_cpu_compositor_is_finite_and_matches_reference(compositor, case_name):
    result = composite_grads(compositor, HARD_CASES[case_name].scene)
    _assert_finite(result, ("image", "alpha", "means2d") + INPUTS)
    expected = _reference(case_name)
    for key in ("image", "alpha"):
        torch.testing.assert_close(result[key], expected[key], atol=1e-5, rtol=0)
    for key in INPUTS + ("means2d",):
        assert_grads_close(result[key], expected[key], key)


@CASES
@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_public_rasterize_is_finite(backend, case_name):
    scene = HARD_CASES[case_name].scene.to(torch.float32).requires_grad_()
    background = torch.full((scene.features.shape[1],), 0.25)
    image, depth, alpha, meta = rasterize(*scene.args(), backend=backend, background=background)
    for name, t in (("image", image), ("depth", depth), ("alpha", alpha)):
        assert torch.isfinite(t).all(), name
    assert image.shape == (scene.height, scene.width, 3) and depth.shape == alpha.shape == (scene.height, scene.width, 1)
    assert ((alpha >= 0) & (alpha <= 1)).all()
    weighted_loss((image, depth, alpha)).backward()
    for name, t in scene.gaussian_tensors.items():
        assert t.grad is not None and torch.isfinite(t.grad).all(), name
    if scene.means.shape[0]:
        assert torch.isfinite(meta.means2d.grad).all()


def test_expected_visibility_of_the_hard_cases():
    # Index 0 is the unusual Gaussian in the two-Gaussian cases (index 1 is an ordinary one).
    visible = {name: rasterize(*case.scene.args(), backend="reference")[3].visible.tolist()
               for name, case in HARD_CASES.items() if name != "stack_1000"}
    for name in ("behind_camera", "straddles_near_plane", "at_camera_centre", "opacity_zero", "off_screen",
                 "far_off_axis_in_front"):
        assert visible[name] == [False, True], name
    for name in ("just_past_near_plane", "tiny_scale", "huge_scale", "flat_scale", "opacity_one"):
        assert visible[name] == [True, True], name
    assert visible["empty"] == []


@pytest.mark.parametrize("compositor", ALL_COMPOSITORS.values(), ids=ALL_COMPOSITORS.keys())
def test_stack_of_1000_stops_early(compositor):
    # 1000 Gaussians with o = 0.6 within 0.1 px of the centre of pixel (14, 18) (the principal
    # point (18.5, 14.5)): there each alpha is just under 0.6, so T = ~0.4^k passes 1e-4 after
    # k = 10 (0.4^10 = 1.05e-4, 0.4^11 = 4.2e-5): the pixel's colour depends on about 10 of the
    # 1000 Gaussians and its alpha stays below 1 - 1e-4.
    scene = HARD_CASES["stack_1000"].scene.to(torch.float32)
    scene.features.requires_grad_(True)
    image, alpha = compositor(project(scene), scene.opacities, scene.features, scene.width, scene.height)
    assert 0.999 < float(alpha.detach()[14, 18, 0]) < 1 - 1e-4
    image[14, 18].sum().backward()
    contributing = int((scene.features.grad.abs().sum(dim=1) > 0).sum())
    assert 9 <= contributing <= 11
