"""The multi-view depth test of the fused static cloud (reflow_plugin/canonical/consistency.py).

A point that more frames see through than agree with is a floater of one frame's depth error and
is dropped; agreeing points, points no other frame sees, and points seen only across another
frame's motion mask stay. On monocular-disparity priors the test must leave fewer points floating
in front of the true surface than fusing every frame does.
"""
from __future__ import annotations

import numpy as np
import pytest

from reflow_plugin.canonical import CanonicalOptions, build_canonical_space
from reflow_plugin.canonical.consistency import FrameDepth, consistent, votes
from reflow_plugin.canonical.geometry import backproject, grid, to_world
from tests.test_real_priors import _depth_ratios, anchors, loaded, real_scene  # noqa: F401 (fixtures)

H, W, F = 24, 32, 30.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])


def _viewmat(x: float) -> np.ndarray:
    """Camera at (x, 0, 0) looking down +z (world -> camera)."""
    V = np.eye(4)
    V[0, 3] = -x
    return V


def _frames(depths: list[np.ndarray], xs: list[float], moving=None) -> list[FrameDepth]:
    return [FrameDepth(d, K, _viewmat(x), None if moving is None else moving[k]) for k, (d, x) in
            enumerate(zip(depths, xs))]


def _points(depth: np.ndarray, x: float) -> np.ndarray:
    rows, cols = grid(H, W, 1)
    return to_world(backproject(depth, K, rows, cols).reshape(-1, 3), _viewmat(x))


def test_floaters_are_dropped_the_surface_and_unseen_points_kept():
    rows, cols = grid(H, W, 1)
    wall = np.full((H, W), 10.0)
    xs = [0.0, 0.5, 1.0]
    floater = wall.copy()
    floater[8:16, 10:20] = 7.0  # frame 0's depth error: a patch 30% in front of the wall
    frames = _frames([floater, wall, wall], xs)
    points = _points(floater, xs[0])
    keep = consistent(points, 0, frames, rows, cols, 0.05)
    patch = np.zeros((H, W), bool)
    patch[8:16, 10:20] = True
    assert not keep.reshape(H, W)[patch].any()  # both other frames look through the patch
    assert keep.reshape(H, W)[~patch].all()  # the wall: supported (or unseen at the image edge)
    # exact depth everywhere: nothing is contradicted
    exact = _frames([wall, wall, wall], xs)
    assert consistent(_points(wall, xs[0]), 0, exact, rows, cols, 0.05).all()
    # a frame that sees none of the points gives no evidence: a patch no other frame sees stays
    far_away = _frames([floater, wall, wall], [0.0, 500.0, 600.0])
    assert consistent(points, 0, far_away, rows, cols, 0.05).all()


def test_points_behind_a_surface_and_across_motion_masks_are_not_voted_against():
    rows, cols = grid(H, W, 1)
    wall = np.full((H, W), 10.0)
    behind = np.full((H, W), 14.0)  # frame 0 puts the wall 40% too far: occluded in the others
    xs = [0.0, 0.5]
    support, against = votes(_points(behind, 0.0), _frames([behind, wall], xs)[1:], rows, cols, 0.05)
    assert not against.any() and not support.any()  # occluded: no evidence either way
    # the floater lands on frame 1's motion mask: that frame says nothing about it
    floater = np.full((H, W), 7.0)
    moving = [np.zeros((H, W), bool), np.ones((H, W), bool)]
    support, against = votes(_points(floater, 0.0), _frames([floater, wall], xs, moving)[1:], rows, cols, 0.05)
    assert not against.any()
    # without the mask it is contradicted wherever it lands in frame 1
    support, against = votes(_points(floater, 0.0), _frames([floater, wall], xs)[1:], rows, cols, 0.05)
    assert against.sum() > 0.5 * H * W
    # points behind the camera or with NaN depth around them: no vote, no error
    nan_frame = _frames([wall, np.full((H, W), np.nan)], xs)[1:]
    support, against = votes(np.array([[0.0, 0.0, -5.0], [0.5, 0.0, 10.0]]), nan_frame, rows, cols, 0.05)
    assert not support.any() and not against.any()


def test_on_monocular_priors_fewer_points_leave_the_true_surface(loaded, anchors):  # noqa: F811
    """Scene scale 50, per-frame affine disparity with a low-frequency error: fusing every frame
    stacks the frames' layers; the test keeps the consistent ones."""
    masks = [c.evaluation_mask.numpy() > 0.5 for c in loaded.train_cameras]
    clouds = {}
    for tol in (0.0, 0.05):
        options = CanonicalOptions(cache=False, max_side=32, voxel=0.0, consistency=tol)
        space = build_canonical_space(loaded, masks, options, anchors=anchors)
        clouds[tol] = (space.static.points, space.report["consistency"])
    fused, _ = clouds[0.0]
    tested, report = clouds[0.05]
    assert report["points"] == len(fused) and report["kept"] == len(tested)
    assert 0.5 * len(fused) < len(tested) < len(fused)
    # floaters: a point in front of the true surface by > 5% in a view it lands in (a correctly placed
    # static point can only be behind it there: occluded); measured 19% of the votes -> 11%
    front = {tol: float(np.mean(_depth_ratios(loaded, p) < 0.95)) for tol, (p, _) in clouds.items()}
    assert front[0.05] < 0.7 * front[0.0], front


def test_depth_agreement_ratios_of_a_cloud_against_sparse_points(loaded, anchors):  # noqa: F811
    """check.cell_ratios (scripts/depth_agreement.py, --canonical_max_depth_error): a cloud ON the
    sparse points agrees (ratio 1), one pushed 10% farther along the camera rays reads 1.1."""
    from reflow_plugin.canonical.check import cell_ratios

    cams = loaded.train_cameras
    nearest, median = cell_ratios(anchors, anchors, cams)
    assert len(nearest) >= len(anchors) and np.median(nearest) == pytest.approx(1.0, abs=1e-6)
    assert np.median(median) == pytest.approx(1.0, abs=0.05)  # other points on the cell count too
    centre = -cams[0].viewmat[:3, :3].double().numpy().T @ cams[0].viewmat[:3, 3].double().numpy()
    farther = centre + 1.1 * (anchors - centre)  # 10% deeper as seen from camera 0
    near0, _ = cell_ratios(farther, anchors, cams[:1])
    assert np.median(near0) == pytest.approx(1.1, rel=0.02)


def test_check_rejects_a_cloud_whose_depth_disagrees_with_the_sparse_points(loaded, anchors):  # noqa: F811
    """--canonical_max_depth_error: a cloud on the sparse points passes, one whose depth is 10% off
    along every camera-0 ray fails with the measurement named and the prior marked rejected."""
    from reflow_plugin.canonical.check import check_initial_cloud

    cams = loaded.train_cameras
    on = check_initial_cloud(anchors, [], cams, anchors, max_depth_error=0.06)
    assert on.passed and on.measurements["depth_error"] < 0.01
    centre = -cams[0].viewmat[:3, :3].double().numpy().T @ cams[0].viewmat[:3, 3].double().numpy()
    off = check_initial_cloud(centre + 1.1 * (anchors - centre), [], cams[:1], anchors, max_depth_error=0.06)
    assert not off.passed and off.measurements["depth_prior_rejected"]
    assert "--canonical_max_depth_error" in off.failure and "10.0%" in off.failure
    unchecked = check_initial_cloud(centre + 1.1 * (anchors - centre), [], cams[:1], anchors)
    assert unchecked.passed  # 0 = not checked (the depth ratio 1.1 is inside the scale check's range)
