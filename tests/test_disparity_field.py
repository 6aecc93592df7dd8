"""The smooth per-frame correction of monocular disparity (reflow_plugin/disparity_field.py)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from reflow_plugin.disparity import fit_disparity, project
from reflow_plugin.disparity_field import bilinear_weights, correct_disparity, field_map, fit_field

W, H, F = 64, 48, 60.0


def _camera():
    """Identity pose, focal F, principal point at the image centre."""
    K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return SimpleNamespace(K=K, viewmat=torch.eye(4, dtype=torch.float64), width=W, height=H)


def _scene(points: int, seed: int = 0):
    """True depth [H, W] (a slanted wall with a box in front) and sparse points on it [P, 3]."""
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    depth = 200.0 + 1.5 * xs + 0.8 * ys
    depth[10:30, 20:40] = 120.0
    rng = np.random.default_rng(seed)
    col, row = rng.integers(0, W, points), rng.integers(0, H, points)
    z = depth[row, col]
    world = np.stack([(col + 0.5 - W / 2) / F * z, (row + 0.5 - H / 2) / F * z, z], 1)
    return depth, world


def _smooth_error(amplitude: float) -> np.ndarray:
    """[H, W] low-frequency multiplicative error of inverse depth (a tilt and a bump)."""
    ys, xs = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    return amplitude * (np.sin(2.5 * xs + 1.0) + (ys - 0.5) + np.cos(3.0 * ys * xs))


def _median_error(disparity: np.ndarray, depth: np.ndarray, points: np.ndarray) -> float:
    """Median relative depth error of `disparity` under its own affine fit to the points (as a run reads it)."""
    x, y, z = project(points, _camera())
    fit = fit_disparity(disparity[np.floor(y).astype(int), np.floor(x).astype(int)], z)
    return float(np.median(np.abs(fit.depth(disparity) / depth - 1.0)))


def test_bilinear_weights_interpolate_the_control_values():
    grid = 4
    x, y = np.array([0.0, W / 2, W, 10.3]), np.array([0.0, H / 3, H, 40.1])
    weights = bilinear_weights(x, y, W, H, grid)
    np.testing.assert_allclose(weights.sum(1), 1.0)
    values = np.add.outer(np.arange(grid) * 2.0, np.arange(grid) * 0.5).ravel()  # a plane in (row, col)
    expected = 2.0 * y / H * (grid - 1) + 0.5 * x / W * (grid - 1)  # bilinear reproduces a plane exactly
    np.testing.assert_allclose(weights @ values, expected, atol=1e-12)
    assert field_map(values, W, H, grid).shape == (H, W)


def test_a_smooth_error_of_the_disparity_is_removed():
    depth, points = _scene(600)
    s, o = 0.01, 0.002
    disparity = (np.exp(_smooth_error(0.05)) / depth - o) / s  # affine map x low-frequency error
    corrected, report = correct_disparity(_camera(), disparity, points, grid=4)
    assert report["corrected"] and report["residual_corrected"] < 0.5 * report["residual"]
    before = _median_error(disparity, depth, points)
    after = _median_error(corrected, depth, points)
    assert before > 0.01 and after < 0.3 * before, (before, after)


def test_a_purely_affine_disparity_is_left_as_it_is():
    depth, points = _scene(600)
    s, o = 0.01, 0.002
    disparity = (1.0 / depth - o) / s
    corrected, report = correct_disparity(_camera(), disparity, points, grid=4)
    assert not report["corrected"] and report["why"] == "no held-out gain"
    assert corrected is disparity or np.array_equal(corrected, disparity)


def test_too_few_points_or_no_fit_leave_the_disparity_unchanged():
    depth, points = _scene(40)  # 40 points: fewer than 4 per control value of a 4 x 4 grid
    disparity = (np.exp(_smooth_error(0.05)) / depth - 0.002) / 0.01
    corrected, report = correct_disparity(_camera(), disparity, points, grid=4)
    assert not report["corrected"] and "inliers" in report["why"]
    assert np.array_equal(corrected, disparity)
    corrected, report = correct_disparity(_camera(), disparity, np.zeros((0, 3)), grid=4)
    assert not report["corrected"] and report["why"] == "no affine fit"


def test_regularised_fit_is_finite_with_empty_controls():
    # every point in one corner: most control values see no data; the smoothness keeps them defined
    weights = bilinear_weights(np.full(50, 1.0), np.full(50, 1.0), W, H, 4)
    values = fit_field(weights, np.full(50, 0.1), 4)
    assert np.isfinite(values).all() and values[0] == pytest.approx(0.1, abs=0.02)


@pytest.mark.parametrize("seed", range(4))
def test_a_moving_object_triangulated_as_static_does_not_bend_the_field(seed):
    # The real-priors truck: a moving object's sparse points, triangulated as if static, sit 3-40%
    # too far in one region of the frame; the nearest of them pass the 3-sigma inlier gate of the
    # affine residuals (whose spread they inflate). The field must follow the static points' smooth
    # error there, not the object's: the biweight's scale is re-estimated from what the field leaves.
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, W, 800), rng.uniform(0, H, 800)

    def truth(px, py):
        return 0.05 * np.sin(2.5 * px / W + 1.0) + 0.05 * (py / H - 0.5)

    r = truth(x, y) + rng.normal(0.0, 0.01, 800)
    on_object = (x > 36) & (x < 56) & (y > 26) & (y < 44)
    r[on_object] = rng.uniform(-0.35, -0.03, on_object.sum())
    # the start scale and the inlier gate as correct_disparity forms them
    sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    inlier = np.abs(r - np.median(r)) <= 3.0 * sigma
    assert (inlier & on_object).sum() >= 5  # some of the object's points are inliers
    values = fit_field(bilinear_weights(x[inlier], y[inlier], W, H, 4), r[inlier], 4, None, sigma)
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    error = np.abs(field_map(values, W, H, 4) - truth(xs, ys))[26:44, 36:56]
    assert float(np.median(error)) < 0.005  # with the start scale held: 0.008-0.027
