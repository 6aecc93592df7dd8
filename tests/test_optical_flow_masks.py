"""DIS optical flow and motion masks from known cameras, against the simulator's ground truth."""
from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from baselines.data import motion_masks
from baselines.data.motion_masks import (MotionMaskOptions, estimate_motion_masks, relative_pose,
                                         static_scene_error)
from baselines.data.optical_flow import consistent, dis_flow, forward_backward_error, sample_bilinear
from baselines.synthetic import get_scene, simulate


def _load(root, n):
    cams = json.loads((root / "gt" / "cameras.json").read_text())["frames"][:n]
    images = [cv2.imread(str(root / "images" / f"{i:03d}.png"))[..., ::-1].copy() for i in range(n)]
    masks = [cv2.imread(str(root / "motion_masks" / f"{i:03d}.png"), 0) > 0 for i in range(n)]
    depths = [np.load(root / "gt" / "depth" / f"{i:03d}.npy") for i in range(n)]
    return images, [np.array(c["K"]) for c in cams], [np.array(c["viewmat"]) for c in cams], masks, depths


@pytest.fixture(scope="module")
def balloon(tmp_path_factory):
    spec = get_scene("balloon", frames=8, width=96, height=72, seed=0)
    return simulate(spec, tmp_path_factory.mktemp("mm") / "balloon", progress=False)


@pytest.fixture(scope="module")
def static_room(tmp_path_factory):
    spec = get_scene("static", frames=6, width=96, height=72, seed=0)
    return simulate(spec, tmp_path_factory.mktemp("mm") / "static", progress=False)


def test_dis_flow_matches_ground_truth(balloon):
    images, *_ = _load(balloon, 4)
    for i in range(3):
        flow = dis_flow(images[i], images[i + 1])
        gt = np.load(balloon / "gt" / "flow_fwd" / f"{i:03d}.npy")
        occluded = cv2.imread(str(balloon / "gt" / "occ_fwd" / f"{i:03d}.png"), 0) > 0
        assert flow.shape == gt.shape and flow.dtype == np.float32
        epe = np.linalg.norm(flow - gt, axis=-1)[~occluded]
        assert np.median(epe) < 0.5, np.median(epe)


def test_identical_frames_give_zero_flow_and_consistency(balloon):
    images, *_ = _load(balloon, 1)
    flow = dis_flow(images[0], images[0])
    assert np.abs(flow).max() < 1e-3
    err, inside = forward_backward_error(flow, flow)
    assert err.max() < 1e-3 and inside.all()
    assert consistent(flow, flow).all()


def test_forward_backward_detects_inconsistency():
    h, w = 20, 30
    fwd = np.zeros((h, w, 2), np.float32)
    fwd[..., 0] = 3.0
    bwd = -fwd.copy()
    bwd[5:10, 10:20] = 5.0  # wrong backward flow in a block
    ok = consistent(fwd, bwd)
    assert ok[0, 0] and not ok[5, 8]
    # pixels pushed out of the image are never "consistent"
    assert not ok[:, -1].any()


def test_sample_bilinear_pixel_centres():
    field = np.arange(12, dtype=np.float32).reshape(3, 4, 1)
    x = np.array([[0.5, 1.0, 3.5]], np.float32)
    y = np.array([[0.5, 0.5, 2.5]], np.float32)
    values, inside = sample_bilinear(field, x, y)
    np.testing.assert_allclose(values[0, :, 0], [0.0, 0.5, 11.0], atol=1e-5)
    assert inside.all()
    _, outside = sample_bilinear(field, np.array([[-1.0]], np.float32), np.array([[1.0]], np.float32))
    assert not outside.any()


def test_bad_images_are_rejected():
    with pytest.raises(ValueError, match="sizes differ"):
        dis_flow(np.zeros((8, 8, 3)), np.zeros((9, 8, 3)))
    with pytest.raises(ValueError, match="NaN"):
        dis_flow(np.full((8, 8, 3), np.nan), np.zeros((8, 8, 3)))
    with pytest.raises(ValueError, match="preset"):
        dis_flow(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), preset="slow")


def test_static_error_is_zero_for_the_true_static_flow():
    K = np.array([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])
    va = np.eye(4)
    vb = np.eye(4)
    vb[:3, 3] = [-0.2, 0.05, 0.0]  # camera b moved right/up
    depth = np.full((30, 40), 4.0)
    y, x = np.mgrid[0:30, 0:40] + 0.5
    # true static flow of a fronto-parallel plane at z=4 under pure translation
    flow = np.stack([np.full_like(x, 50.0 * -0.2 / 4.0), np.full_like(y, 50.0 * 0.05 / 4.0)], -1)
    assert static_scene_error(flow, K, va, K, vb).max() < 1e-6
    assert static_scene_error(flow, K, va, K, vb, depth).max() < 1e-6
    # a flow perpendicular to the epipolar lines (here: vertical extra motion) is flagged
    moved = flow + np.array([0.0, 2.0])
    assert static_scene_error(moved, K, va, K, vb).min() > 1.0


def test_pure_rotation_uses_the_homography():
    K = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    angle = np.deg2rad(2.0)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    vb = np.eye(4)
    vb[:3, :3] = R
    rotation, translation = relative_pose(np.eye(4), vb)
    assert np.allclose(translation, 0) and np.allclose(rotation, R)
    y, x = np.mgrid[0:24, 0:32] + 0.5
    q = np.stack([x, y, np.ones_like(x)], -1)
    p = q @ (K @ R @ np.linalg.inv(K)).T
    flow = p[..., :2] / p[..., 2:] - q[..., :2]
    err = static_scene_error(flow.astype(np.float32), K, np.eye(4), K, vb)
    assert np.isfinite(err).all() and err.max() < 1e-3


def test_masks_find_the_balloon(balloon):
    images, Ks, viewmats, truth, depths = _load(balloon, 8)
    masks, report = estimate_motion_masks(images, Ks, viewmats)
    assert report.epipolar_only and all(len(p) >= 2 for p in report.pairs)
    ious = [(m & t).sum() / max((m | t).sum(), 1) for m, t in zip(masks, truth) if t.sum() > 20]
    assert np.mean(ious) > 0.4, ious
    false_positive = np.mean([(m & ~t).mean() for m, t in zip(masks, truth)])
    assert false_positive < 0.01
    depth_masks, depth_report = estimate_motion_masks(images, Ks, viewmats, depths)
    assert not depth_report.epipolar_only
    depth_ious = [(m & t).sum() / max((m | t).sum(), 1) for m, t in zip(depth_masks, truth) if t.sum() > 20]
    assert np.mean(depth_ious) > 0.6, depth_ious


def test_static_scene_gives_empty_masks(static_room):
    images, Ks, viewmats, _, _ = _load(static_room, 6)
    masks, report = estimate_motion_masks(images, Ks, viewmats)
    assert max(report.coverage) < 0.005


def test_degenerate_inputs():
    image = np.zeros((16, 16, 3), np.uint8)
    masks, report = estimate_motion_masks([image], [np.eye(3)], [np.eye(4)])
    assert len(masks) == 1 and not masks[0].any() and report.pairs == [[]]
    assert estimate_motion_masks([], [], [])[0] == []
    with pytest.raises(ValueError, match="intrinsics"):
        estimate_motion_masks([image, image], [np.eye(3)], [np.eye(4), np.eye(4)])
    with pytest.raises(ValueError, match="frame 1"):
        estimate_motion_masks([image, np.zeros((8, 8, 3), np.uint8)], [np.eye(3)] * 2, [np.eye(4)] * 2)
    opts = MotionMaskOptions(offsets=(1,))
    masks, report = estimate_motion_masks([image, image], [np.eye(3)] * 2, [np.eye(4)] * 2, options=opts)
    assert not any(m.any() for m in masks)


def test_mask_offsets_reach_the_estimate_and_its_cache_key(balloon, tmp_path, monkeypatch):
    """ReFlow's --mask_offsets pairs each frame with those neighbours, and masks cached under one
    pairing are never read back for another."""
    import torch

    from baselines.data import motion_masks
    from reflow_plugin import labels

    images, Ks, viewmats, _, depths = _load(balloon, 8)
    cameras = [SimpleNamespace(image=torch.from_numpy(im.astype(np.float32) / 255), K=torch.from_numpy(K),
                               viewmat=torch.from_numpy(v), time=k / 7, frame_index=k, image_name=f"{k:03d}",
                               width=96, height=72) for k, (im, K, v) in enumerate(zip(images, Ks, viewmats))]
    seen = []
    real = motion_masks.estimate_motion_masks

    def spy(*args, **kwargs):
        masks, report = real(*args, **kwargs)
        seen.append(report.pairs)
        return masks, report

    monkeypatch.setattr(labels, "estimate_motion_masks", spy)
    wide = labels.estimated_masks(cameras, tmp_path, depths, offsets=(-4, 4))
    assert seen[-1][0] == [4] and seen[-1][5] == [1]  # frame 0 pairs with 4 only; frame 5 with 1 (9 is past the end)
    default = labels.estimated_masks(cameras, tmp_path, depths)
    assert len(seen) == 2 and seen[-1][3] == [1, 2, 4, 5]  # computed again, not read from the (-4, 4) cache
    assert any((w != d).any() for w, d in zip(wide, default))
    labels.estimated_masks(cameras, tmp_path, depths)
    assert len(seen) == 2  # the same pairing is read from the cache


def test_a_slow_object_is_found_by_the_slow_pairing_only(tmp_path):
    """An object moving 0.5 px per frame in front of a still camera: the frames 1-2 apart see 0.75 px
    of motion in the median over the pairs (under the 1 px needed: nothing flagged); the slow
    pairing (frames 4-8 apart, median 2.5 px, 2 px needed) finds it and adds nothing on the still
    background. Its cache key differs from the default's."""
    import torch

    from reflow_plugin import labels

    rng = np.random.default_rng(0)
    background = cv2.GaussianBlur(rng.uniform(0, 1, (72, 96, 3)).astype(np.float32), (0, 0), 1.0)
    patch = cv2.GaussianBlur(rng.uniform(0, 1, (20, 20, 3)).astype(np.float32), (0, 0), 1.0)
    frames, truth = 17, []
    images = []
    for k in range(frames):
        shift = np.float32([[1, 0, 30 + 0.5 * k], [0, 1, 26]])  # sub-pixel motion, bilinear
        layer = cv2.warpAffine(patch, shift, (96, 72), flags=cv2.INTER_LINEAR)
        alpha = cv2.warpAffine(np.ones((20, 20), np.float32), shift, (96, 72), flags=cv2.INTER_LINEAR)[..., None]
        images.append(alpha * layer + (1 - alpha) * background)
        truth.append(alpha[..., 0] > 0.5)
    K = np.array([[80.0, 0, 48], [0, 80.0, 36], [0, 0, 1]])
    cameras = [SimpleNamespace(image=torch.from_numpy(im), K=torch.from_numpy(K),
                               viewmat=torch.eye(4, dtype=torch.float64), time=k / (frames - 1), frame_index=k,
                               image_name=f"{k:03d}", width=96, height=72)
               for k, im in enumerate(images)]
    fast = labels.estimated_masks(cameras, None)
    both = labels.estimated_masks(cameras, None, slow_offsets=(-8, -6, -4, 4, 6, 8))
    middle = range(4, 13)
    assert sum(int((fast[k] & truth[k]).sum()) for k in middle) < 0.05 * sum(int(truth[k].sum()) for k in middle)
    found = sum(int((both[k] & truth[k]).sum()) for k in middle) / sum(int(truth[k].sum()) for k in middle)
    wrong = sum(int((both[k] & ~truth[k]).sum()) for k in middle) / sum(int((~truth[k]).sum()) for k in middle)
    assert found > 0.5 and wrong < 0.02, (found, wrong)
    assert labels._cache_key(cameras, False) != labels._cache_key(cameras, False, slow_offsets=(-4, 4))


def test_each_unordered_pair_is_flowed_once_and_the_masks_do_not_change(balloon, monkeypatch):
    """Frame a pairs with a + o and a + o with a: both use one DIS run of the pair (PairFlows)."""
    images, Ks, viewmats, *_ = _load(balloon, 8)
    options = MotionMaskOptions(slow_offsets=(-4, 4))
    runs = []
    real_flow_pair = motion_masks.flow_pair
    monkeypatch.setattr(motion_masks, "flow_pair", lambda a, b: runs.append(1) or real_flow_pair(a, b))
    shared, _ = estimate_motion_masks(images, Ks, viewmats, options=options)
    # unordered pairs 1 or 2 frames apart (7 + 6) and 4 apart (4), once each
    assert len(runs) == 7 + 6 + 4

    class EveryRequest(motion_masks.PairFlows):  # the reference: each frame runs its own pairs
        def __call__(self, a, b):
            self.computed += 1
            return motion_masks.flow_pair(self.images[a], self.images[b])

    runs.clear()
    monkeypatch.setattr(motion_masks, "PairFlows", EveryRequest)
    reference, _ = estimate_motion_masks(images, Ks, viewmats, options=options)
    assert len(runs) == 2 * (7 + 6 + 4)
    assert sum(mask.sum() for mask in reference) > 0  # the balloon is found, so the comparison means something
    for mask, expected in zip(shared, reference):
        np.testing.assert_array_equal(mask, expected)
