"""Issue 40: switches and checks that do what they say.

Occlusion switches refused where they cannot run (partner mode), the inverse-depth refinement's
scale without sparse points and its one vote per region, the depth-prior gate and the disparity
field's acceptance measured out of sample, the stall guard's flat-loss window for any number of
views and its handling of a stage that hides every Gaussian, no fit for a flat disparity map.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from reflow_plugin.canonical import inverse as inverse_module
from reflow_plugin.canonical.geometry import grid, rays
from reflow_plugin.disparity import FrameFit, coverage_weights, fit_disparity, fit_frames, project

W, H, F = 64, 48, 50.0


# ------------------------------------------------------------------ 1. occlusion in partner mode
def test_occlusion_switches_are_refused_in_partner_mode():
    from reflow_plugin.matching import check_occlusion_mode

    for occlusion, cam_occlusion, named in ((True, False, "occlusion"), (False, True, "cam_occlusion"),
                                            (True, True, "occlusion,cam_occlusion")):
        with pytest.raises(ValueError, match=f"--enable {named} needs --pair_mode both"):
            check_occlusion_mode(occlusion, cam_occlusion, "partner")
        check_occlusion_mode(occlusion, cam_occlusion, "both")
    check_occlusion_mode(False, False, "partner")


def test_occlusion_in_partner_mode_is_one_error_line_before_loading(tiny_scene, tmp_path, capsys):
    from baselines.fourdgs.app import run_cli, train_from_argv
    from tests.test_trainer import base_argv

    argv = base_argv(tiny_scene, tmp_path / "run", 1, 1, "--plugin", "reflow", "--enable", "occlusion,cam_occlusion")
    with pytest.raises(SystemExit) as stop:
        run_cli(lambda: train_from_argv(argv) and 0)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--enable occlusion,cam_occlusion needs --pair_mode both" in err[0], err
    assert not (tmp_path / "run" / "point_cloud").exists() and not (tmp_path / "run" / "reflow" / "static.ply").exists()
    # in pair_mode both the switches build and train
    both = base_argv(tiny_scene, tmp_path / "both", 1, 1, "--plugin", "reflow", "--enable", "occlusion,cam_occlusion",
                     "--pair_mode", "both", "--flow_vis_every", "0", "--save_iterations", "1")
    summary = train_from_argv(both)
    assert {"occlusion", "cam_occlusion"} <= summary.trainer.hooks.plugins[0].enabled
    # a run continued from a saved point_cloud folder builds no initial cloud: refused all the same
    upgrade = base_argv(tiny_scene, tmp_path / "upgrade", 0, 1, "--plugin", "reflow", "--enable", "occlusion",
                        "--start_checkpoint", str(tmp_path / "both"))
    with pytest.raises(SystemExit) as stop:
        run_cli(lambda: train_from_argv(upgrade) and 0)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--enable occlusion needs --pair_mode both" in err[0], err


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
@pytest.mark.parametrize("flags, named", [(["--backend", "gsplat"], "backend='gsplat' cannot run"),
                                          (["--device", "cuda"], "--device 'cuda' requested")])
def test_a_backend_or_device_this_machine_lacks_stops_before_the_folder_is_made(tiny_scene, tmp_path, flags, named):
    from baselines.fourdgs.app import build_trainer

    run = tmp_path / "run"
    with pytest.raises(ValueError, match=named):
        build_trainer(["-s", str(tiny_scene), "-m", str(run), "--quiet", *flags])
    assert not run.exists()  # no folder, no dataset read, no cloud built


# ------------------------------------------------------------------ 2, 3. the inverse-depth refinement
class _Plane:
    """Cameras along x looking at the tilted plane Z = 10 + 0.5 Y; inverse_depth gives the TRUE
    inverse depth, so FrameFit(1, 0) is exact and FrameFit(s, 0) puts every depth at 1 / s of the truth."""

    def __init__(self, xs: list[float]) -> None:
        self.K = [np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]]) for _ in xs]
        self.viewmats = []
        for x in xs:
            viewmat = np.eye(4)
            viewmat[0, 3] = -x
            self.viewmats.append(viewmat)
        self.cameras = [SimpleNamespace(extras={}, image_name=f"{k:03d}") for k in range(len(xs))]

    def grid(self, full: bool = False):
        return grid(H, W, 1 if full else 2)

    def inverse_depth(self, n: int, full: bool = False):
        rows, cols = self.grid(full)
        ray = rays(self.K[n], rows, cols)
        depth = 10.0 / (1.0 - 0.5 * ray[..., 1])
        return 1.0 / depth, np.ones_like(depth)


def _depth_ratio(provider: _Plane, state, n: int) -> float:
    """Median of the refined depth over the true depth in frame n."""
    d = provider.inverse_depth(n, full=True)[0]
    return float(np.median(d / (state.scale * d + state.shift)))


def test_without_sparse_points_the_refinement_keeps_the_common_scale():
    """The view term cannot see a common scale (exactly, on a plane): without the gauge the three
    frames' depth drifted to 0.981-0.983 of the truth in 50 steps; with it 0.9999-1.0015."""
    provider, frames = _Plane([-1.0, 0.0, 1.0]), [0, 1, 2]
    weights = {n: np.ones((24, 32)) for n in frames}
    fits = {n: FrameFit(1.0 + 0.05 * (n - 1), 0.0, "bounds") for n in frames}  # right on average, +-5% per frame
    states, report = inverse_module.align_inverse(provider, frames, weights, fits, {}, window=2, iterations=50)
    ratios = [_depth_ratio(provider, states[n], n) for n in frames]
    assert max(abs(r - 1.0) for r in ratios) < 0.005, ratios
    # the refinement did its job: the frames agree with each other
    assert report["residual"]["views"] < 0.1 * report["residual_init"]["views"], report
    assert report["anchors"] == 0 and "no sparse point" in report["scale_anchor"]
    # off (0 steps): the initial fits as they are
    off, off_report = inverse_module.align_inverse(provider, frames, weights, fits, {}, window=2, iterations=0)
    assert [off[n].scale for n in frames] == pytest.approx([fits[n].scale for n in frames])
    assert off_report["residual"]["views"] == pytest.approx(off_report["residual_init"]["views"])


def test_sparse_points_pull_a_wrong_start_scale_to_the_truth():
    """With anchors, shrinking every depth is not a minimum: a start 1.3x too near comes back."""
    provider, frames = _Plane([-1.0, 0.0, 1.0]), [0, 1, 2]
    weights = {n: np.ones((24, 32)) for n in frames}
    fits = {n: FrameFit(1.3, 0.0, "sparse") for n in frames}
    rng = np.random.default_rng(0)
    anchors = {}
    for n in frames:
        d = provider.inverse_depth(n, full=True)[0]
        row, col = rng.integers(0, H, 60), rng.integers(0, W, 60)
        anchors[n] = (d[row, col], 1.0 / d[row, col])
    states, report = inverse_module.align_inverse(provider, frames, weights, fits, anchors, window=2, iterations=50)
    before = 1 / 1.3
    ratios = [_depth_ratio(provider, states[n], n) for n in frames]
    assert max(abs(r - 1.0) for r in ratios) < 0.02 < abs(before - 1.0), ratios
    assert report["residual"]["anchors"] < 0.1 * report["residual_init"]["anchors"]
    assert report["scale_anchor"] == "sparse points"


def test_the_anchor_term_counts_one_vote_per_region():
    """450 points on one 4x4-pixel patch, 8% too far, against 150 right ones spread over the frame:
    counted per point the refined depth moved 7.2% too far; per region it stays."""
    provider = _Plane([0.0])
    d_full = provider.inverse_depth(0, full=True)[0]
    rng = np.random.default_rng(0)
    x = np.r_[rng.uniform(0, W, 150), rng.uniform(40, 44, 450)]
    y = np.r_[rng.uniform(0, H, 150), rng.uniform(10, 14, 450)]
    d = d_full[y.astype(int), x.astype(int)]
    z = 1.0 / d
    z[150:] *= 1.08
    votes = coverage_weights(x, y, W, H)
    states, _ = inverse_module.align_inverse(provider, [0], {0: np.ones((24, 32))}, {0: FrameFit(1.0, 0.0, "sparse")},
                                             {0: (d, z, votes)}, iterations=50)
    assert abs(_depth_ratio(provider, states[0], 0) - 1.0) < 0.005


# ------------------------------------------------------------------ 4, 5. out-of-sample gates
def _camera():
    K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return SimpleNamespace(K=K, viewmat=torch.eye(4, dtype=torch.float64), width=W, height=H, extras={},
                           time=0.0, frame_index=0, image_name="000")


def _wall(points: int, noise: float, outliers: float, seed: int = 0):
    """(disparity [H, W] exactly affine in the inverse depth of a slanted wall, sparse points [P, 3]
    on it with relative depth noise and a fraction of gross outliers 2-4x too far)."""
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    depth = 100.0 + 1.5 * xs + 0.8 * ys
    disparity = (1.0 / depth - 0.001) / 0.02
    rng = np.random.default_rng(seed)
    col, row = rng.integers(0, W, points), rng.integers(0, H, points)
    z = depth[row, col] * (1.0 + noise * rng.standard_normal(points))
    wrong = rng.uniform(size=points) < outliers
    z[wrong] *= rng.uniform(2.0, 4.0, wrong.sum())
    world = np.stack([(col + 0.5 - W / 2) / F * z, (row + 0.5 - H / 2) / F * z, z], 1)
    return disparity, world


def test_the_depth_prior_gate_reads_held_out_points_and_reports_all_points():
    """35% gross outliers: the inlier median is in the gate's range, every point's is not."""
    from reflow_plugin.canonical.check import check_initial_cloud, prior_residual
    from reflow_plugin.disparity import summary

    cam = _camera()
    disparity, points = _wall(600, 0.12, 0.35)
    fit = fit_frames([cam], [disparity], points)[0]
    assert fit.source == "sparse"
    assert fit.residual < 0.1 < fit.residual_all and fit.held_out > 0.1, fit.as_dict()
    report = dict(summary([fit]), frames={cam.image_name: fit.as_dict()})
    residual = prior_residual(report)
    assert residual == {"held_out": fit.held_out, "inliers": fit.residual, "all": fit.residual_all}
    verdict = check_initial_cloud(points, [], [cam], points, residual, max_fit_residual=0.1)
    assert not verdict.passed and "held out by image region" in verdict.failure
    assert verdict.measurements["fit_residual_inliers"] < 0.1 < verdict.measurements["fit_residual"]
    # too few points to hold half out (60: 30 a half is the least): no held-out figure; the gate
    # reads every point in sample and says so
    few = fit_frames([cam], [disparity], points[:50])[0]
    assert few.source == "sparse" and few.held_out is None
    few_report = dict(summary([few]), frames={cam.image_name: few.as_dict()})
    verdict = check_initial_cloud(points, [], [cam], points, prior_residual(few_report), max_fit_residual=0.01)
    assert not verdict.passed and "in sample (too few points" in verdict.failure
    assert verdict.measurements["fit_residual"] == few.residual_all
    # where the smooth correction was kept, its own held-out residual stands for the frame's
    assert prior_residual(report, {cam.image_name: 0.02})["held_out"] == 0.02
    assert prior_residual({"frames": {"000": FrameFit(1.0, 0.0, "bounds").as_dict()}}) is None


def test_held_out_points_come_from_the_other_regions():
    from reflow_plugin.disparity import region_folds

    x, y = np.random.default_rng(0).uniform(0, W, (2, 2000)) * np.array([[1.0], [H / W]])
    fold = region_folds(x, y, W, H)
    size = max(W, H) / 4
    block = np.floor(x / size) + 100 * np.floor(y / size)
    for b in np.unique(block):  # each square lies wholly in one half, its four neighbours in the other
        assert len(set(fold[block == b])) == 1
    assert 0.4 < fold.mean() < 0.6
    # a held-out point's nearest training point lies across its square's edge: several pixels away
    # (the median), where a random half puts one within about half a pixel
    train, held = np.stack([x[fold], y[fold]], 1), np.stack([x[~fold], y[~fold]], 1)
    nearest = np.sqrt(((held[:, None] - train[None]) ** 2).sum(-1)).min(1)
    assert np.median(nearest) > 3.0  # random halves of 2000 points: ~0.5 px


def test_the_field_is_accepted_on_held_out_regions_with_votes():
    """The field's "before" is exactly the affine fit's held-out residual by region (vote-weighted,
    every held-out point), the figure the depth-prior gate reads for an uncorrected frame."""
    from reflow_plugin.disparity import held_out_residual
    from reflow_plugin.disparity_field import correct_disparity

    cam = _camera()
    disparity, points = _wall(600, 0.03, 0.2)
    _, report = correct_disparity(cam, disparity, points, grid=4)
    x, y, z = project(points, cam)
    d = disparity[np.floor(y).astype(int), np.floor(x).astype(int)]
    assert report["held_out_before"] == pytest.approx(held_out_residual(d, z, x, y, W, H), rel=1e-9)
    assert not report["corrected"] and report["why"] == "no held-out gain"  # nothing smooth to correct


def test_the_plugin_fits_the_field_outside_the_datasets_masks(monkeypatch):
    import reflow_plugin.canonical_construction as plugin_module
    from reflow_plugin.plugin import ReFlowPlugin

    seen = []

    def spy(camera, disparity, points, grid=4, mask=None):
        seen.append(mask)
        return disparity, {"corrected": False, "points": 0, "why": "spy"}

    monkeypatch.setattr(plugin_module, "correct_disparity", spy)
    mask = torch.zeros(H, W)
    mask[:10, :10] = 1.0
    cams = [SimpleNamespace(disparity=torch.ones(H, W), mask=mask, image_name="000"),
            SimpleNamespace(disparity=torch.ones(H, W), mask=None, image_name="001")]
    ctx = SimpleNamespace(train_cameras=cams, point_cloud=SimpleNamespace(points=np.ones((5, 3))),
                          point_cloud_source="triangulated")
    ReFlowPlugin()._corrected_disparity(ctx)
    assert seen[0] is not None and seen[0].dtype == bool and seen[0].sum() == 100 and seen[1] is None


# ------------------------------------------------------------------ 6. the stall guard
def _ctx(cams, batch, loss, alpha=0.5, hidden=None, count=10):
    return SimpleNamespace(views=[SimpleNamespace(alpha=torch.full((4, 4, 1), alpha))], metrics={"loss": loss},
                           loss=None, batch=batch, model=SimpleNamespace(get_xyz=torch.zeros(count, 3)),
                           train_cameras=cams, point_cloud_source="plugin", scene=SimpleNamespace(near_far=None),
                           stage="coarse", iteration=1, hidden=hidden)


def _views(count: int):
    viewmat = torch.eye(4)
    viewmat[2, 3] = 5.0
    K = torch.tensor([[10.0, 0.0, 8.0], [0.0, 10.0, 8.0], [0.0, 0.0, 1.0]])
    return [SimpleNamespace(uid=k, viewmat=viewmat, K=K, width=16, height=16, image_name=f"{k:03d}")
            for k in range(count)]


def _sampled(cams, steps: int, seed: int = 0):
    """The host's sampler: each pass draws every view once, in random order (batch size 1)."""
    from baselines.fourdgs.sampler import CameraSampler

    sampler = CameraSampler(cams, seed=seed)
    return [sampler.next_batch(1) for _ in range(steps)]


def test_a_frozen_run_with_more_views_than_the_window_is_stopped():
    """250 views at batch size 1: no view repeats within 200 steps; a frozen run (each view's loss
    constant, different between views) is stopped once views come round again."""
    from baselines.fourdgs.stall_guard import StallGuard, TrainingStalled

    cams = _views(250)
    guard = StallGuard(200)
    with pytest.raises(TrainingStalled, match="loss stayed flat") as stop:
        for step, batch in enumerate(_sampled(cams, 600), 1):
            guard.observe(_ctx(cams, batch, 0.1 + 0.001 * batch[0].uid))
    assert 250 < step < 250 + 50 and "drawn again gave their first loss again" in str(stop.value)


def test_a_frozen_run_with_more_views_than_the_guards_wait_is_stopped():
    """1000 views: the first window's views come round only after 1000 steps, past WAIT x 200."""
    from baselines.fourdgs.stall_guard import WAIT, StallGuard, TrainingStalled

    cams = _views(1000)
    guard = StallGuard(200)
    with pytest.raises(TrainingStalled, match="loss stayed flat"):
        for step, batch in enumerate(_sampled(cams, 2500), 1):
            guard.observe(_ctx(cams, batch, 0.1 + 0.0001 * batch[0].uid))
    assert WAIT * 200 <= 1000 < step < 1100


def test_a_learning_run_with_many_views_is_not_stopped():
    from baselines.fourdgs.stall_guard import StallGuard

    cams = _views(250)
    guard = StallGuard(200)
    for step, batch in enumerate(_sampled(cams, 600), 1):
        guard.observe(_ctx(cams, batch, 0.1 + 0.001 * batch[0].uid + 1.0 / step))  # falls, per view
    assert guard.decided and len(guard.again) >= 8


def test_a_frozen_run_with_few_views_is_stopped_at_the_window():
    from baselines.fourdgs.stall_guard import StallGuard, TrainingStalled

    cams = _views(4)
    guard = StallGuard(50)
    with pytest.raises(TrainingStalled, match="loss stayed flat"):
        for step, batch in enumerate(_sampled(cams, 200), 1):
            guard.observe(_ctx(cams, batch, 0.1 + 0.01 * batch[0].uid))
    assert step == 50


def test_steps_with_every_gaussian_hidden_are_not_counted():
    """Every Gaussian labelled dynamic: the coarse stage hides them all. The guard waits for the
    stage that shows them instead of blaming the initial cloud; a partly hidden model still counts."""
    from baselines.fourdgs.stall_guard import StallGuard, TrainingStalled

    cams = _views(4)
    guard = StallGuard(50)
    everything = torch.ones(10, dtype=torch.bool)
    for step, batch in enumerate(_sampled(cams, 120), 1):  # coarse: nothing rendered, loss flat
        guard.observe(_ctx(cams, batch, 0.5, alpha=0.0, hidden=everything))
    assert guard.seen == 0 and guard.invisible_since is None
    for step, batch in enumerate(_sampled(cams, 120), 1):  # fine: shown, learning
        guard.observe(_ctx(cams, batch, 1.0 / step, hidden=None))
    assert guard.seen == 120
    partly = StallGuard(50)
    some = torch.zeros(10, dtype=torch.bool)
    some[:5] = True
    with pytest.raises(TrainingStalled, match="no Gaussian was visible"):
        for batch in _sampled(cams, 120):
            partly.observe(_ctx(cams, batch, 0.5, alpha=0.0, hidden=some))


def test_a_stage_with_every_pixel_weighted_out_is_not_a_flat_loss():
    """Motion masks covering every frame: the coarse stage's loss is exactly 0 (measured on a
    12-frame 32x32 scene, --disable comp_init: stopped at iteration 30 as "flat, 0 to 0"); the
    fine stage learns. Left out of the flat-loss test; a render that stays empty still counts."""
    from baselines.fourdgs.stall_guard import StallGuard, TrainingStalled

    cams = _views(4)
    guard = StallGuard(50)
    for batch in _sampled(cams, 120):
        guard.observe(_ctx(cams, batch, 0.0))
    assert guard.zero_losses == 120 and not guard.losses and not guard.decided
    for step, batch in enumerate(_sampled(cams, 120), 1):
        guard.observe(_ctx(cams, batch, 1.0 / step))
    assert guard.decided and guard.seen == 240
    empty = StallGuard(50)
    with pytest.raises(TrainingStalled, match="no Gaussian was visible"):
        for batch in _sampled(cams, 120):
            empty.observe(_ctx(cams, batch, 0.0, alpha=0.0))


def test_reflow_marks_the_hidden_gaussians_in_the_coarse_stage():
    from reflow_plugin.plugin import ReFlowPlugin
    from reflow_plugin.separated_modeling import HIDDEN_OPACITY

    table = torch.tensor([True, False, True])
    model = SimpleNamespace(deformation_table=table, registered_buffers={}, _opacity=torch.zeros(3, 1))
    model.register_gaussian_buffer = lambda name, value: model.registered_buffers.__setitem__(name, value)
    model.pop_gaussian_buffer = lambda name: model.registered_buffers.pop(name)
    ctx = SimpleNamespace(model=model, stage="coarse", hidden=None)
    plugin = ReFlowPlugin()
    plugin._hide_dynamic_in_coarse(ctx)
    assert HIDDEN_OPACITY in model.registered_buffers and ctx.hidden.tolist() == [True, False, True]
    ctx.stage = "fine"
    plugin._hide_dynamic_in_coarse(ctx)
    assert ctx.hidden is None and model._opacity[:, 0].tolist() == [0.0, 0.0, 0.0]


# ------------------------------------------------------------------ 7. a flat disparity map
def test_a_flat_disparity_map_gives_no_fit():
    depth = np.random.default_rng(0).uniform(40.0, 400.0, 300)
    assert fit_disparity(np.full(300, 0.7), depth) is None
    assert fit_disparity(np.full(300, 0.7) + 1e-9 * np.arange(300), depth) is None  # flat to rounding
    ramp = (1.0 / depth - 0.001) / 0.004  # the same depths with a real disparity
    assert fit_disparity(ramp, depth).scale == pytest.approx(0.004, rel=1e-6)


# ------------------------------------------------------------------ 8. schedule flags refused before any loading
@pytest.mark.parametrize("flags, named", [
    (("--iterations", "0"), "--iterations 0"),
    (("--position_lr_final", "0"), "--position_lr_init 0.00016 with --position_lr_final 0"),
    (("--grid_lr_init", "0"), "--grid_lr_init 0 with --grid_lr_final 0.00016"),
    (("--deformation_lr_final", "0"), "--deformation_lr_final 0"),
])
def test_schedule_flags_that_cannot_train_are_one_line_before_the_dataset_is_read(tmp_path, capsys, flags, named):
    """Before: --iterations 0 was refused once the dataset was loaded, a rate pair of 0 and > 0 only
    once the initial cloud was built (ReFlow: after its canonical space), without the flag's name.
    The dataset named here does not exist: the flag must be what the line names."""
    from baselines.fourdgs.app import run_cli, train_from_argv
    from tests.test_trainer import base_argv

    argv = base_argv(tmp_path / "no_such_dataset", tmp_path / "run", 1, 1, *flags)
    with pytest.raises(SystemExit) as stop:
        run_cli(lambda: train_from_argv(argv) and 0)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and named in err[0] and "no_such_dataset" not in err[0], err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("flag", ["--position_lr_init", "--grid_lr_final", "--feature_lr", "--opacity_lr",
                                  "--scaling_lr", "--rotation_lr"])
def test_a_negative_learning_rate_is_a_flag_error(flag, capsys):
    from arguments import parse_train_args

    with pytest.raises(SystemExit) as stop:
        parse_train_args([flag, "-0.001"])
    assert stop.value.code == 2
    assert f"argument {flag}: must be >= 0, got -0.001" in capsys.readouterr().err


@pytest.mark.parametrize("flags, named", [(("--train_cameras", "1,2"), "--train_cameras"),
                                          (("--test_every", "5", "--test_cameras", "0"), "--test_cameras, --test_every")])
def test_panoptic_only_flags_on_another_dataset_are_one_error_line(tiny_scene, tmp_path, capsys, flags, named):
    """Before: the panoptic reader's split flags were dropped without a word on any other dataset, so
    a user's held-out cameras silently became the dataset's own split."""
    from baselines.fourdgs.app import run_cli, train_from_argv
    from tests.test_trainer import base_argv

    argv = base_argv(tiny_scene, tmp_path / "run", 1, 1, *flags)
    with pytest.raises(SystemExit) as stop:
        run_cli(lambda: train_from_argv(argv) and 0)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{named}: read by the panoptic reader only" in err[0], err
    assert not (tmp_path / "run" / "point_cloud").exists()


@pytest.mark.parametrize("flag, value, message", [("--timenet_width", "0", "must be > 0, got 0"),
                                                   ("--timenet_output", "0", "must be > 0, got 0"),
                                                   ("--timebase_pe", "-1", "must be >= 0, got -1")])
def test_a_time_network_that_cannot_be_built_is_a_flag_error(flag, value, message, capsys):
    """Before: torch failed when the model was built, after the initial cloud."""
    from arguments import parse_train_args

    with pytest.raises(SystemExit) as stop:
        parse_train_args([flag, value])
    assert stop.value.code == 2
    assert f"argument {flag}: {message}" in capsys.readouterr().err
