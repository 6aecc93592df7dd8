"""A wide multi-camera rig read monocularly (reflow_plugin.rig): frames paired by camera, not by time.

The simulator's `hard_baseline` scene is the class: 4 rig cameras 1 m apart, frame t from camera
t mod 4, so consecutive frames are 13-41 degrees apart (CMU Panoptic basketball's five dome
cameras: 26-68). Its ground-truth masks and depth score what the pairing by camera buys.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from baselines.data import load_scene
from baselines.data.motion_masks import estimate_motion_masks
from baselines.synthetic import get_scene, simulate
from reflow_plugin.canonical import CanonicalOptions, build_canonical_space
from reflow_plugin.canonical.check import check_initial_cloud
from reflow_plugin.canonical.geometry import backproject, grid, to_world
from reflow_plugin.canonical import providers
from reflow_plugin.canonical.providers import FlowProvider, guide_depth
from reflow_plugin.labels import estimated_masks, pairing_sequences
from reflow_plugin.rig import pose_groups, viewing_angle_deg, wide_rig


@pytest.fixture(scope="module")
def rig_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rig") / "hard_baseline"
    simulate(get_scene("hard_baseline", frames=24, width=128, height=96, seed=0), path, progress=False)
    return path


@pytest.fixture(scope="module")
def rig(rig_path):
    return load_scene(rig_path, eval=False)


@pytest.fixture(scope="module")
def truth(rig):
    return [c.mask.numpy() > 0.5 for c in rig.train_cameras]


def _viewmats(name: str) -> list[np.ndarray]:
    spec = get_scene(name)
    return [np.linalg.inv(spec.camera.pose(f, f / (spec.frames - 1))[0]) for f in range(spec.frames)]


def _iou(masks, truth) -> float:
    return float(np.mean([(m & t).sum() / max((m | t).sum(), 1) for m, t in zip(masks, truth) if t.any()]))


def _gt_depth(path: Path, camera) -> np.ndarray:
    return np.load(path / "gt" / "depth" / f"{camera.image_name}.npy").astype(np.float64)


def _sparse_points(path: Path, cameras, truth, per_frame: int = 10) -> np.ndarray:
    """[P, 3] static points from the ground-truth depth outside the masks (a sparse SfM stand-in)."""
    rng = np.random.default_rng(0)
    points = []
    for cam, mask in zip(cameras, truth):
        rows, cols = grid(cam.height, cam.width, 1)
        world = to_world(backproject(_gt_depth(path, cam), cam.K.double().numpy(), rows, cols),
                         cam.viewmat.double().numpy())[~mask]
        points.append(world[rng.choice(len(world), per_frame, replace=False)])
    return np.concatenate(points)


def test_wide_rig_is_told_from_narrow_rigs_videos_and_still_cameras():
    assert wide_rig(_viewmats("hard_baseline"))
    assert not wide_rig(_viewmats("skating"))  # 12 cameras a few degrees apart: time order is viewpoint order
    assert not wide_rig(_viewmats("balloon"))  # one still camera
    swing = [np.linalg.inv(get_scene("hard_baseline").camera.pose(k % 4, 0.0)[0]) for k in range(4)]
    assert not wide_rig(swing)  # every pose new (a video): nothing recurs
    groups = pose_groups(_viewmats("hard_baseline"))
    assert groups.tolist() == [k % 4 for k in range(24)]
    assert viewing_angle_deg(swing[0], swing[0]) == pytest.approx(0.0, abs=1e-5)


def test_rig_masks_pair_each_camera_with_its_own_frames(rig, truth):
    """Time neighbours are other rig cameras, where DIS fails; one camera's frames see a still scene."""
    cameras = rig.train_cameras
    sequences = pairing_sequences(cameras)
    groups = pose_groups([c.viewmat.numpy() for c in cameras])
    assert sorted(len(s) for s in sequences) == [6, 6, 6, 6]
    assert all(len(set(groups[s].tolist())) == 1 for s in sequences)  # one rig camera each
    assert all(np.diff([cameras[i].time for i in s]).min() > 0 for s in sequences)  # in time order
    by_camera = estimated_masks(cameras, None)
    images = [c.image.numpy() for c in cameras]
    by_time, _ = estimate_motion_masks(images, [c.K.numpy() for c in cameras], [c.viewmat.numpy() for c in cameras])
    assert _iou(by_time, truth) < 0.1  # what the time order gave
    assert _iou(by_camera, truth) > 0.6


def test_flow_provider_triangulates_rig_frames_with_the_nearest_cameras(rig_path, rig, truth):
    cameras = rig.train_cameras
    anchors = _sparse_points(rig_path, cameras, truth)
    guided = FlowProvider(cameras, stride=1, anchors=anchors)
    assert guided.rig and "|rig|guided" in guided.key()
    viewmats = [c.viewmat.double().numpy() for c in cameras]
    for n in range(8):
        partners = guided.partners(n)
        assert len(partners) == 2 and all(guided.groups[m] != guided.groups[n] for m in partners)
        others = sorted({viewing_angle_deg(viewmats[n], viewmats[m]) for m in range(len(cameras))
                         if guided.groups[m] != guided.groups[n]})
        assert sorted(viewing_angle_deg(viewmats[n], viewmats[m]) for m in partners) == pytest.approx(others[:2])
    guide = guided.guide(0)
    assert guide.shape == (cameras[0].height, cameras[0].width) and np.isfinite(guide).all() and (guide > 0).all()
    assert guide_depth(anchors[:2], guided.K[0], guided.viewmats[0], 96, 128) is None  # too few points: no guide

    def error_and_coverage(provider):
        errors, covered = [], []
        for n in range(len(cameras)):
            depth, conf = provider.depth(n)
            good = (conf > 0.5) & ~truth[n]
            covered.append(good.mean())
            errors.append(np.median(np.abs(depth[good] / _gt_depth(rig_path, cameras[n])[good] - 1)))
        return float(np.median(errors)), float(np.mean(covered))

    error, coverage = error_and_coverage(guided)
    time_order = FlowProvider(cameras, stride=1)
    time_order.rig = False  # the time neighbours, DIS from zero
    error_time, coverage_time = error_and_coverage(time_order)
    assert error < 0.025 and coverage > 0.7  # measured 0.018 / 0.75
    assert error_time > 1.5 * error and coverage_time < coverage - 0.08  # measured 0.035 / 0.63


def test_rig_canonical_space_is_triangulated_without_the_time_ordered_alignment(rig_path, rig, truth, monkeypatch):
    anchors = _sparse_points(rig_path, rig.train_cameras, truth)
    options = CanonicalOptions(provider="flow", max_side=64, cache=False, iterations=30)

    def depth_error(space) -> float:
        check = check_initial_cloud(space.static.points, [], rig.train_cameras, anchors)
        return check.measurements["depth_error"]

    space = build_canonical_space(rig, truth, options, anchors=anchors)
    assert space.report["alignment"]["mode"].startswith("none (rig")
    assert "|rig|guided" in space.report["provider"] and len(space.static) > 500
    monkeypatch.setattr(providers, "wide_rig", lambda viewmats: False)  # time neighbours, aligned
    by_time = build_canonical_space(rig, truth, options, anchors=anchors)
    assert by_time.report["alignment"]["mode"] == "coarse_to_fine"
    # measured 0.027 by camera, 0.092 by time
    assert depth_error(space) < 0.04 and depth_error(by_time) > 1.5 * depth_error(space)


def test_rig_pairs_benchmark_reports_both_pairings(rig_path, tmp_path, capsys):
    """benchmarks/rig_pairs.py on the simulator's rig (dataset points: its triangulated cloud)."""
    from benchmarks.rig_pairs import main

    out = tmp_path / "pairs.json"
    assert main(["-s", str(rig_path), "-r", "1", "--frames", "2", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["wide rig"] and report["poses"] == 4
    assert set(report["masks"]) == {"time order", "by camera"}
    guided, by_time = report["triangulation"]["nearest rig cameras, guided"], report["triangulation"]["time neighbours, from zero"]
    assert guided["pairs"] == 4 and guided["confident"] > by_time["confident"]
    assert "wide rig True" in capsys.readouterr().out
    assert main(["-s", str(tmp_path / "missing")]) == 2
