"""Complete canonical space (reflow_plugin.canonical, issue 9) on a small simulator scene.

Ground truth: the simulator's exact cameras and gt/depth. The depth provider reads gt/depth with
controlled per-frame scale drift, noise and outliers, which the alignment must undo.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from baselines.data import load_scene
from baselines.data.triangulation import triangulate_static_points
from baselines.fourdgs.app import REPO_ROOT, build_trainer, finish_run
from baselines.synthetic import get_scene, simulate
from reflow_plugin.canonical import CanonicalOptions, build_canonical_space, make_provider, options_from_params
from reflow_plugin.canonical.alignment import align_frames
from reflow_plugin.canonical.coarse_to_fine import align_sequence, clip_edges, clips
from reflow_plugin.canonical.geometry import backproject, grid, rotation_angle_deg, to_world, umeyama
from reflow_plugin.canonical.providers import PairPrediction
from reflow_plugin.labels import project
from reflow_plugin.params import ReFlowParams
from tests.test_trainer import FAST

ERRORS = dict(depth_source="gt", drift=0.15, noise=0.02, outliers=0.01, max_side=32, iterations=250)
CHAMFER_BOUND = 0.02  # x the median scene depth (about 3 m): 6 cm


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory) -> Path:
    """Skating, 16 frames at 64x48: a 2-row rig of 6 camera positions (baseline 1 m), a moving skater."""
    path = tmp_path_factory.mktemp("canonical") / "skating"
    simulate(get_scene("skating", frames=16, width=64, height=48, seed=0), path, progress=False)
    return path


@pytest.fixture(scope="module")
def scene(scene_path):
    return load_scene(scene_path, eval=False)


@pytest.fixture(scope="module")
def masks(scene):
    return [c.mask.numpy() > 0.5 for c in scene.train_cameras]


def _true_static(scene, masks) -> np.ndarray:
    """[P, 3] world points of every frame's gt depth outside the motion masks (the true surface)."""
    points = []
    for cam, mask in zip(scene.train_cameras, masks):
        depth = np.load(scene.source_path / "gt" / "depth" / f"{cam.image_name}.npy").astype(np.float64)
        rows, cols = grid(cam.height, cam.width, 1)
        X = backproject(depth, cam.K.double().numpy(), rows, cols)
        points.append(to_world(X[~mask & np.isfinite(depth)], cam.viewmat.double().numpy()))
    return np.concatenate(points)


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    return 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


@pytest.fixture(scope="module")
def surface(scene, masks):
    truth = _true_static(scene, masks)
    depth = np.median([np.median(np.load(scene.source_path / "gt" / "depth" / f"{c.image_name}.npy"))
                       for c in scene.train_cameras])
    return truth, float(depth)


@pytest.fixture(scope="module")
def aligned(scene, masks):
    return build_canonical_space(scene, masks, CanonicalOptions(clip_len=6, **ERRORS))


def test_free_poses_are_recovered(scene):
    """Free poses (only frame 0 anchors the gauge): relative poses within 1 degree and 2% of the extent.

    Milder errors than the fixed-camera tests (0.5% noise, no outliers): a frame's scale and its
    position along the optical axis are nearly interchangeable for a narrow view, so free poses
    need cleaner pointmaps (measured: 2% noise + 1% outliers give ~8% of the extent)."""
    cams = scene.train_cameras
    provider = make_provider(cams, scene.source_path, CanonicalOptions(**dict(ERRORS, noise=0.005, outliers=0.0)))
    frames = list(range(len(cams)))
    h, w = (len(a) for a in provider.grid())
    states, report = align_sequence(provider, frames, {n: np.ones((h, w)) for n in frames}, mode="full",
                                    free_poses=True, iterations=200)
    truth = [c.viewmat.double().numpy() for c in cams]
    centre = lambda V: -V[:3, :3].T @ V[:3, 3]  # noqa: E731
    est_c = np.stack([centre(states[n].viewmat) for n in frames])
    true_c = np.stack([centre(V) for V in truth])
    s, R, t = umeyama(est_c, true_c)
    extent = np.linalg.norm(true_c[:, None] - true_c[None], axis=-1).max()
    position_error = np.linalg.norm(s * est_c @ R.T + t - true_c, axis=1).max() / extent
    angle = max(rotation_angle_deg(states[a].viewmat[:3, :3] @ states[b].viewmat[:3, :3].T
                                   @ (truth[a][:3, :3] @ truth[b][:3, :3].T).T)
                for a in frames for b in frames)
    assert report["residual"] <= report["stages"][0]["residual_init"] + 1e-9
    assert angle < 1.0 and position_error < 0.02, (angle, position_error)
    # the drifted provider alone is far off: without the alignment the scales disagree by ~15%
    assert np.std(np.log(provider.scales)) > 0.05


def test_fused_static_cloud_is_on_the_surface_and_better_than_without_align(scene, masks, surface, aligned):
    truth, depth = surface
    raw = build_canonical_space(scene, masks, CanonicalOptions(clip_len=6, align=False, **ERRORS))
    error, error_raw = _chamfer(aligned.static.points, truth) / depth, _chamfer(raw.static.points, truth) / depth
    assert error < CHAMFER_BOUND, error
    assert error_raw > 1.5 * error, (error, error_raw)
    assert np.isfinite(aligned.static.points).all() and len(aligned.static) > 500
    report = aligned.report
    assert report["alignment"]["mode"] == "coarse_to_fine" and report["alignment"]["clips"] == 3
    assert report["alignment"]["keyframes"] == [scene.train_cameras[k].image_name for k in (0, 6, 12)]
    json.dumps(report)  # JSON-able


def _coverage(points: np.ndarray, scene, masks, k: int) -> float:
    """Fraction of frame k's dynamic pixels hit by a projected point within 5% of the true depth."""
    cam = scene.train_cameras[k]
    depth = np.load(scene.source_path / "gt" / "depth" / f"{cam.image_name}.npy")
    if len(points) == 0:
        return 0.0
    x, y, z = project(np.asarray(points, np.float64), cam)
    col, row = np.floor(x).astype(int), np.floor(y).astype(int)
    ok = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
    ok[ok] &= np.abs(z[ok] - depth[row[ok], col[ok]]) < 0.05 * depth[row[ok], col[ok]]
    hit = np.zeros_like(masks[k])
    hit[row[ok], col[ok]] = True
    return float((hit & masks[k]).sum() / masks[k].sum())


def test_dynamic_cloud_covers_the_moving_object(scene, masks, aligned):
    k = aligned.reference_frame
    assert k is not None and masks[k].sum() == max(m.sum() for m in masks) or masks[k].sum() > 0
    assert _coverage(aligned.dynamic.points, scene, masks, k) > 0.8
    host = triangulate_static_points(scene.train_cameras, seed=0)  # SfM drops keypoints in the masks
    assert _coverage(np.asarray(host.points).reshape(-1, 3), scene, masks, k) < 0.1


class _Broken:
    """Wraps a provider: zero confidence on some pairs, NaN in some outputs."""

    def __init__(self, inner, zero_pairs=(), nan_pairs=(), nan_frames=(), empty_frames=()):
        self.inner, self.zero, self.nan_pairs = inner, set(zero_pairs), set(nan_pairs)
        self.nan_frames, self.empty_frames = set(nan_frames), set(empty_frames)

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def depth(self, n, full=False):
        d, c = self.inner.depth(n, full)
        if n in self.empty_frames:
            return np.full_like(d, np.nan), c
        if n in self.nan_frames:
            d = d.copy()
            d[::2] = np.nan
        return d, c

    def pair(self, i, j):
        p = self.inner.pair(i, j)
        if (i, j) in self.zero:
            return PairPrediction(p.X_ii, p.X_ji, 0 * p.C_ii, 0 * p.C_ji)
        if (i, j) in self.nan_pairs:
            X = p.X_ii.copy()
            X[:, ::3] = np.nan
            return PairPrediction(X, p.X_ji, p.C_ii, p.C_ji)
        return p


def _weights(provider, frames):
    h, w = (len(a) for a in provider.grid())
    return {n: np.ones((h, w)) for n in frames}


def _finite(states):
    return all(np.isfinite([s.scale, s.shift]).all() and np.isfinite(s.viewmat).all() for s in states.values())


def test_degenerate_pair_graphs(scene):
    cams = scene.train_cameras
    inner = make_provider(cams, scene.source_path, CanonicalOptions(**dict(ERRORS, iterations=30)))
    frames = [0, 1, 2, 3]
    # an edge with zero confidence is dropped and reported
    states, report = align_frames(_Broken(inner, zero_pairs={(0, 1)}), frames, [(0, 1), (1, 2), (2, 3)],
                                  _weights(inner, frames), iterations=30)
    assert report["dropped_edges"] == [[0, 1]] and report["unaligned"] == [cams[0].image_name] and _finite(states)
    # disconnected: fixed cameras align each component (a lone frame gets the median scale) ...
    states, report = align_frames(inner, frames, [(0, 1), (2, 3)], _weights(inner, frames), iterations=30)
    assert report["unaligned"] == [] and _finite(states)
    for n in frames:  # every component found its metric scale from the camera baselines
        assert states[n].scale == pytest.approx(1 / inner.scales[n], rel=0.05)
    # ... free poses cannot: the error names the cut-off frames
    with pytest.raises(ValueError, match=f"disconnected.*{cams[2].image_name}"):
        align_frames(inner, frames, [(0, 1), (2, 3)], _weights(inner, frames), free_poses=True)
    # a single frame
    with pytest.raises(ValueError, match="at least 2 frames, got 1"):
        align_sequence(inner, [0], _weights(inner, [0]))
    # NaN from the provider: those pixels carry no weight, the result stays finite
    states, report = align_frames(_Broken(inner, nan_pairs={(1, 2)}, nan_frames={3}), frames,
                                  [(0, 1), (1, 2), (2, 3)], _weights(inner, frames), iterations=30)
    assert _finite(states) and report["edges"] == 3
    with pytest.raises(ValueError, match=f"no finite positive depth for frame 2 \\({cams[2].image_name}\\)"):
        align_frames(_Broken(inner, empty_frames={2}), frames, [(0, 1), (1, 2)], _weights(inner, frames))


def test_clips_and_degenerate_frames(scene, masks):
    assert clips(list(range(7)), 3) == [[0, 1, 2], [3, 4, 5], [6]]
    assert clip_edges([4, 5, 6], window=8) == [(4, 5), (4, 6), (5, 6)]  # clip shorter than the window
    # an entirely dynamic frame: no static point from it, its scale falls back, nothing NaN
    full = [m.copy() for m in masks]
    full[5][:] = True
    space = build_canonical_space(scene, full, CanonicalOptions(clip_len=4, window=8, **dict(ERRORS, iterations=40)))
    assert np.isfinite(space.static.points).all() and np.isfinite(space.dynamic.points).all()
    unaligned = [u for stage in space.report["alignment"]["stages"] for u in stage["unaligned"]]
    assert scene.train_cameras[5].image_name in unaligned
    # free poses: the keyframe graph first, each clip's keyframe held at its state (the gauge)
    provider = make_provider(scene.train_cameras, scene.source_path, CanonicalOptions(**dict(ERRORS, noise=0.005)))
    frames = list(range(len(scene.train_cameras)))
    states, report = align_sequence(provider, frames, _weights(provider, frames), clip_len=6, free_poses=True,
                                    iterations=20)
    assert report["keyframes_held"] and report["stages"][0]["stage"] == "keyframes" and _finite(states)
    key_states, _ = align_frames(provider, [0, 6, 12], [(0, 6), (0, 12), (6, 12)], _weights(provider, frames),
                                 free_poses=True, iterations=20)
    np.testing.assert_allclose(states[6].viewmat, key_states[6].viewmat, atol=1e-9)
    # the one-frame last clip (16 frames, clips of 5) is paired with the previous frame
    space = build_canonical_space(scene, masks, CanonicalOptions(clip_len=5, **dict(ERRORS, iterations=20)))
    assert space.report["alignment"]["clips"] == 4 and len(space.static) > 0


def test_cache_reuse_and_invalidation(scene, masks, tmp_path):
    options = CanonicalOptions(clip_len=8, **dict(ERRORS, iterations=20))
    first = build_canonical_space(scene, masks, options, cache_dir=tmp_path)
    second = build_canonical_space(scene, masks, options, cache_dir=tmp_path)
    assert (first.report["cache"], second.report["cache"]) == ("miss", "hit")
    np.testing.assert_array_equal(first.static.points, second.static.points)
    np.testing.assert_array_equal(first.dynamic.points, second.dynamic.points)
    assert second.reference_frame == first.reference_frame
    other = build_canonical_space(scene, masks, CanonicalOptions(clip_len=8, **dict(ERRORS, iterations=20, drift=0.3)),
                                  cache_dir=tmp_path)
    moved = [m.copy() for m in masks]
    moved[0][0, 0] = not moved[0][0, 0]
    again = build_canonical_space(scene, moved, options, cache_dir=tmp_path)
    assert other.report["cache"] == "miss" and again.report["cache"] == "miss"
    assert len(list(tmp_path.glob("space_*.npz"))) == 3 and not list(tmp_path.glob("*.tmp"))
    off = build_canonical_space(scene, masks, CanonicalOptions(clip_len=8, cache=False, **dict(ERRORS, iterations=20)),
                                cache_dir=tmp_path)
    assert off.report["cache"] == "off"


def test_flow_provider_triangulates_the_static_scene(scene, masks):
    """DIS flow + known cameras: metric depth without any depth input. Coarse at 64x48 (parallax of a
    few pixels): the bound checks metric scale and shape, not precision."""
    provider = make_provider(scene.train_cameras, scene.source_path, CanonicalOptions(provider="flow", max_side=64))
    assert provider.name == "flow"
    depth, conf = provider.depth(1)
    truth = np.load(scene.source_path / "gt" / "depth" / f"{scene.train_cameras[1].image_name}.npy")
    good = (conf > 0.5) & ~masks[1]
    assert good.mean() > 0.3
    ratio = depth[good] / truth[good]
    assert abs(np.median(ratio) - 1) < 0.1 and np.median(np.abs(ratio - 1)) < 0.2


def test_params_flags_and_options():
    p = ReFlowParams()
    options = options_from_params(p)
    assert options.align and options.clip_len == 25 and options.provider == "auto"
    p.canonical_align, p.canonical_clip_len = False, 7
    options = options_from_params(p)
    assert not options.align and options.clip_len == 7


def test_a_one_frame_clip_is_a_flag_error(capsys):
    """--canonical_clip_len 1 passed the > 0 check and stopped the pairwise alignment (where it runs),
    after the motion masks and the depth fits."""
    from arguments import parse_train_args

    with pytest.raises(SystemExit):
        parse_train_args(["--canonical_clip_len", "1"], extra_groups={"ReFlowParams": ReFlowParams})
    assert "argument --canonical_clip_len: must be at least 2 (a clip pairs its frames), got 1" in capsys.readouterr().err
    args = parse_train_args(["--canonical_clip_len", "2"], extra_groups={"ReFlowParams": ReFlowParams})
    assert args.extra["ReFlowParams"].canonical_clip_len == 2


def test_plugin_uses_the_canonical_space(scene_path, tmp_path):
    out = tmp_path / "run"
    argv = ["-s", str(scene_path), "-m", str(out), "--configs", str(REPO_ROOT / "arguments/synthetic/default.py"),
            "--coarse_iterations", "2", "--iterations", "2", *FAST, "--plugin", "reflow", "--flow_vis_every", "0",
            "--canonical_iters", "20", "--canonical_clip_len", "8"]
    trainer = build_trainer(argv)
    finish_run(trainer, trainer.train())
    results = json.loads((out / "results.json").read_text())["reflow"]
    assert results["initial_cloud"].startswith("canonical space:") and "keyframe-seeded" in results["initial_cloud"]
    # the dataset's disparity with the host's triangulated points: scale first, in inverse depth
    assert results["canonical"]["alignment"]["mode"] == "inverse depth (anchored)"
    assert results["canonical_check"]["passed"] and results["canonical_check"]["used"] == "canonical space"
    assert (out / "reflow" / "static.ply").is_file() and (out / "reflow" / "dynamic.ply").is_file()
    assert list((out / "reflow" / "canonical").glob("space_*.npz"))
    # --no-canonical_align with a single reference frame: the paper's w/o align cloud
    out2 = tmp_path / "raw"
    trainer = build_trainer([*argv[:3], str(out2), *argv[4:], "--no-canonical_align", "--dynamic_keyframes", "1"])
    finish_run(trainer, trainer.train())
    results = json.loads((out2 / "results.json").read_text())["reflow"]
    assert "(reference frame)" in results["initial_cloud"]
    # a single reference frame: --curriculum_fraction (0.5) spreads the pairs out from it
    plugin = trainer.hooks.plugins[0]
    assert plugin.keyframe_times == [plugin.depth_cameras[plugin.reference].time] and plugin._uses_curriculum
    assert results["canonical"]["alignment"]["mode"] == "none (w/o align)"  # exact disparity: the check passes
    assert results["canonical_check"]["passed"] and not results["canonical_check"]["failures"]


def test_canonical_max_points_help_says_the_voxel_0_cloud_is_not_limited():
    """static_cloud grows the voxel to meet --canonical_max_points; with --canonical_voxel 0 there is
    no voxel to grow and every point is kept. The help claimed a limit in every case."""
    import dataclasses

    help_text = {f.name: f.metadata["help"] for f in dataclasses.fields(ReFlowParams)}["canonical_max_points"]
    assert "not applied with --canonical_voxel 0" in help_text


def test_a_canonical_space_without_static_points_says_the_hosts_cloud_stood_in(tiny_scene, tmp_path):
    """Every pixel masked as moving: the canonical space has no static point and the host's cloud is
    the static cloud. Before, the run recorded "canonical space" as used and a depth check that had
    compared the host's cloud with itself as passed (DAVIS blackswan), as if the fused cloud had been
    checked."""
    import shutil

    import cv2

    from baselines.fourdgs.app import train_from_argv
    from tests.test_trainer import base_argv

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    for path in sorted((scene / "motion_masks").iterdir()):
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        mask[:] = 255
        cv2.imwrite(str(path), mask)
    train_from_argv(base_argv(scene, tmp_path / "run", 0, 1, "--plugin", "reflow", "--flow_vis_every", "0"))
    info = json.loads((tmp_path / "run" / "results.json").read_text())["reflow"]
    assert info["canonical_check"]["used"].startswith("canonical space without static points (the host's")
    assert info["initial_cloud"].startswith("canonical space without static points")
