"""Degenerate and extreme scenes: finite outputs and finite gradients w.r.t. every input."""
from __future__ import annotations

import pytest
import torch

from baselines.render import rasterize
from raster_cases import (
    GRAD_KEYS, HARD_CASES, VALUE_ATOL, assert_matches, composite_grads, named_scene, over_all_compositors,
    over_cpu_compositors, project, reference_grads, weighted_loss,
)

CASES = pytest.mark.parametrize("case_name", HARD_CASES.keys())


@CASES
def test_reference_is_finite(case_name):
    result = reference_grads(case_name)
    for key in ("image", "alpha") + GRAD_KEYS:
        assert result[key] is not None, f"no gradient reached {key}"
        assert torch.isfinite(result[key]).all(), f"{key} is not finite"


@CASES
@over_cpu_compositors
def test_cpu_compositor_is_finite_and_matches_reference(compositor, case_name):
    assert_matches(composite_grads(compositor, named_scene(case_name)), reference_grads(case_name))


def _public_render(scene, backend: str) -> dict:
    scene = scene.to(torch.float32).requires_grad_()
    background = torch.full((scene.features.shape[1],), 0.25)
    image, depth, alpha, meta = rasterize(*scene.args(), backend=backend, background=background)
    assert image.shape == (scene.height, scene.width, 3) and depth.shape == alpha.shape == (scene.height, scene.width, 1)
    weighted_loss((image, depth, alpha)).backward()
    out = {"image": image.detach(), "depth": depth.detach(), "alpha": alpha.detach()}
    out.update({k: v.grad for k, v in scene.gaussian_tensors.items()})
    if scene.means.shape[0]:
        out["means2d"] = meta.means2d.grad
    return out


@CASES
def test_public_rasterize_is_finite_and_cpu_matches_reference(case_name):
    results = {backend: _public_render(HARD_CASES[case_name].scene, backend) for backend in ("reference", "cpu")}
    for backend, result in results.items():
        for key, value in result.items():
            assert value is not None and torch.isfinite(value).all(), f"{backend}: {key}"
        assert ((result["alpha"] >= 0) & (result["alpha"] <= 1)).all()
    cpu, ref = results["cpu"], results["reference"]
    for key in ("image", "alpha"):
        torch.testing.assert_close(cpu[key], ref[key], atol=VALUE_ATOL, rtol=0)
    # Depth = sum(w z) / alpha is compared relative to the depth itself (the scenes reach z = 20).
    torch.testing.assert_close(cpu["depth"], ref["depth"], atol=VALUE_ATOL, rtol=1e-5)


def test_expected_visibility_of_the_hard_cases():
    # Index 0 is the unusual Gaussian in the two-Gaussian cases (index 1 is an ordinary one).
    visible = {name: project(case.scene).visible.tolist() for name, case in HARD_CASES.items()}
    for name in ("behind_camera", "straddles_near_plane", "at_camera_centre", "opacity_zero", "off_screen",
                 "far_off_axis_in_front"):
        assert visible[name] == [False, True], name
    for name in ("just_past_near_plane", "tiny_scale", "huge_scale", "flat_scale", "opacity_one"):
        assert visible[name] == [True, True], name
    assert visible["empty"] == []
    assert not any(visible["all_off_screen"])
    # z = -1, -0.005, 0, 0.008 are culled (z < 0.01); z = 0.02, 0.05, 0.3 are in front.
    assert visible["near_plane_scan"][-7:] == [False] * 4 + [True] * 3
    zero_and_one = visible["opacity_zero_and_one"]
    assert any(zero_and_one[0::2]) and not any(zero_and_one[1::2])  # opacity 0 is culled, 1 is not


@over_all_compositors
def test_stack_of_1000_stops_early(compositor):
    # 1000 Gaussians with o = 0.6 within 0.1 px of the centre of pixel (14, 18) (the principal
    # point (18.5, 14.5)): there each alpha is just under 0.6, so T = ~0.4^k passes 1e-4 after
    # k = 10 (0.4^10 = 1.05e-4, 0.4^11 = 4.2e-5): the pixel's colour depends on about 10 of the
    # 1000 Gaussians and its alpha stays below 1 - 1e-4.
    scene = named_scene("stack_1000")
    scene.features.requires_grad_(True)
    image, alpha = compositor(project(scene), scene.opacities, scene.features, scene.width, scene.height)
    assert 0.999 < float(alpha.detach()[14, 18, 0]) < 1 - 1e-4
    image[14, 18].sum().backward()
    contributing = int((scene.features.grad.abs().sum(dim=1) > 0).sum())
    assert 9 <= contributing <= 11


@over_cpu_compositors
def test_gaussians_behind_the_stop_get_no_gradient_like_reference(compositor):
    # 1000 Gaussians a few pixels wide around one pixel, depths tied in groups of 4: every pixel
    # stops early, so most Gaussians are never composited and get exactly zero gradient; which
    # ones must be decided exactly as in the reference (same order on ties, same stop).
    expected = reference_grads("stack_1000_depth_ties")
    got = composite_grads(compositor, named_scene("stack_1000_depth_ties"))
    assert float(expected["alpha"].max()) > 1 - 2e-4
    untouched = (expected["features"] == 0).all(dim=1)
    assert untouched.sum() > 900
    assert torch.equal((got["features"] == 0).all(dim=1), untouched)
