"""The ReFlow plugin in the host: registration, bad input, skips, gradients, labels, a short run."""
from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from arguments import ConfigError
from baselines.data import load_scene
from baselines.fourdgs.app import REPO_ROOT, build_trainer, finish_run, render_from_argv
from baselines.fourdgs.plugins import PluginError, available_plugins
from baselines.fourdgs.renderer import composite_view, prepare_view
from baselines.synthetic import get_scene, simulate
from reflow_plugin.labels import vote_labels
from reflow_plugin.matching import MatchingConfig, dynamic_threshold, pair_losses
from reflow_plugin.pairs import PairError, PairSampler, curriculum_radius
from reflow_plugin.params import ReFlowParams
from reflow_plugin.plugin import ReFlowPlugin
from reflow_plugin.seeding import reference_frame, seed_dynamic_points
from tests.test_trainer import FAST


def _argv(scene: Path, out: Path, coarse: int, fine: int, *extra: str) -> list[str]:
    return ["-s", str(scene), "-m", str(out), "--configs", str(REPO_ROOT / "arguments/synthetic/default.py"),
            "--coarse_iterations", str(coarse), "--iterations", str(fine), *FAST, "--plugin", "reflow",
            "--flow_vis_every", "0", *extra]


def test_registered_through_the_entry_point():
    assert "reflow" in available_plugins()
    assert ReFlowPlugin.components[:4] == ("comp_init", "separation", "full_flow", "cam_flow")


def test_bad_input_is_rejected_before_training(tiny_scene, tmp_path, capsys):
    with pytest.raises(PluginError, match="unknown component 'fullflow'"):
        build_trainer(_argv(tiny_scene, tmp_path / "a", 1, 1, "--disable", "fullflow"))
    with pytest.raises(SystemExit) as stop:  # a bad flag value: argparse's one-line error, exit code 2
        build_trainer(_argv(tiny_scene, tmp_path / "b", 1, 1, "--lambda_ff", "-1"))
    assert stop.value.code == 2 and "--lambda_ff: must be >= 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:  # a zero offset pairs a frame with itself
        build_trainer(_argv(tiny_scene, tmp_path / "b", 1, 1, "--mask_slow_offsets", "-4", "0"))
    assert stop.value.code == 2 and "--mask_slow_offsets: must be" in capsys.readouterr().err
    config = tmp_path / "bad.py"
    config.write_text("ReFlowParams = dict(lambda_cf=-0.5)\n")
    with pytest.raises(ConfigError, match="lambda_cf"):
        build_trainer(_argv(tiny_scene, tmp_path / "b", 1, 1, "--configs", str(config)))
    single = simulate(get_scene("balloon", frames=2, width=16, height=16), tmp_path / "two", progress=False)
    # --eval: frame 0 tests, 1 frame trains; refused with the scene, before the model folder is claimed
    with pytest.raises(ValueError, match="1 training frame.*--plugin reflow needs at least 2 training frames"):
        build_trainer(_argv(single, tmp_path / "c", 1, 1))
    assert not (tmp_path / "c").exists()


def test_slow_mask_pairing_is_on_by_default_and_0_turns_it_off(tiny_scene, tmp_path):
    assert ReFlowPlugin().slow_mask_offsets() == (-8, -6, -4, 4, 6, 8)
    off = build_trainer(_argv(tiny_scene, tmp_path / "off", 1, 1, "--mask_slow_offsets", "0"))
    assert off.hooks.plugins[0].slow_mask_offsets() == ()
    wide = build_trainer(_argv(tiny_scene, tmp_path / "wide", 1, 1, "--mask_slow_offsets", "-5", "5"))
    assert wide.hooks.plugins[0].slow_mask_offsets() == (-5, 5)


def test_pair_sampler_and_curriculum():
    cams = [types.SimpleNamespace(time=t, frame_index=i) for i, t in enumerate(np.linspace(0, 1, 10))][::-1]
    sampler = PairSampler(cams, window=2, seed=0)
    for _ in range(200):
        i, j = sampler.sample()
        assert i != j and 1 <= abs(cams[i].frame_index - cams[j].frame_index) <= 2
        i, j = sampler.sample(center=5, radius=1)
        assert {cams[i].frame_index, cams[j].frame_index} <= {4, 5, 6}
    state = sampler.state_dict()
    first = [sampler.sample() for _ in range(5)]
    sampler.load_state_dict(state)
    assert [sampler.sample() for _ in range(5)] == first
    assert curriculum_radius(0, 100, 9) == 1 and curriculum_radius(50, 100, 9) == 5 and curriculum_radius(100, 100, 9) == 9
    with pytest.raises(PairError):
        PairSampler(cams[:1], 2)


def test_reference_frame_and_seeds_back_project_exactly(tiny_scene):
    scene = load_scene(tiny_scene, eval=True)
    cams = scene.train_cameras
    masks = [c.mask.numpy() > 0.5 for c in cams]
    k = reference_frame(cams, masks)
    assert k is not None and masks[k].sum() == max(m.sum() for m in masks) or masks[k].sum() > 0
    depth = 1.0 / cams[k].disparity.numpy()  # the simulator's disparity is exactly 1 / depth
    seeds = seed_dynamic_points(cams[k], masks[k], depth, 10_000)
    assert len(seeds) == int(masks[k].sum())
    from reflow_plugin.labels import project
    x, y, z = project(seeds.points.astype(np.float64), cams[k])
    rows, cols = np.nonzero(masks[k])
    np.testing.assert_allclose(x, cols + 0.5, atol=1e-3)
    np.testing.assert_allclose(z, depth[rows, cols], rtol=1e-5)
    labels = vote_labels(seeds.points, [cams[k]], [masks[k]])
    assert labels.all()


@pytest.fixture(scope="module")
def built(tiny_scene, tmp_path_factory):
    trainer = build_trainer(_argv(tiny_scene, tmp_path_factory.mktemp("built") / "run", 2, 2, "--pair_mode", "both"))
    trainer.build()
    trainer._begin_stage("fine", 2)  # optimizer built; the dynamic Gaussians visible
    return trainer


def test_labels_and_seeds_from_the_dataset_masks(built):
    plugin = built.hooks.plugins[0]
    table = built.ctx.model.deformation_table
    assert plugin.info["mask_source"] == "dataset"
    assert int(table.sum()) > 0 and int((~table).sum()) > 0
    assert "seeded dynamic points" in plugin.info["initial_cloud"]
    low, high = built.ctx.model.deformation.get_aabb[1], built.ctx.model.deformation.get_aabb[0]
    dynamic = built.ctx.model.get_xyz.detach()[table]
    assert ((dynamic >= low) & (dynamic <= high)).all()  # the dynamic HexPlane box holds the dynamic points


def _pair_views(trainer, stage="fine", times=(0, 3)):
    ctx = trainer.ctx
    plugin = trainer.hooks.plugins[0]
    ctx.stage, ctx.batch = stage, [trainer.train_cameras[i] for i in times]
    ctx.views = [prepare_view(ctx.model, c, stage) for c in ctx.batch]
    for k, view in enumerate(ctx.views):
        composite_view(view, ctx.background, plugin.extra_features(ctx, k))
    return ctx.views, plugin


def test_flow_matching_gradients_reach_both_times_and_the_network(built):
    model = built.ctx.model
    views, plugin = _pair_views(built)
    for view in views:
        view.state.means.retain_grad()
    result = pair_losses(views, MatchingConfig(), use_full=True, use_cam=True)
    assert set(result.losses) == {"ff_mc", "ff_cr", "cf_mc", "cf_cr"}
    model.optimizer.zero_grad(set_to_none=True)
    result.losses["ff_mc"].backward()
    dynamic = model.deformation_table
    for view in views:  # L_mc reaches the Gaussians at t_a AND at t_b
        assert view.state.means.grad[dynamic].abs().sum() > 0
    assert model._xyz.grad[dynamic].abs().sum() > 0
    heads = model.deformation.deformation_net.pos_deform[3]
    assert heads.weight.grad is not None and heads.weight.grad.abs().sum() > 0


def test_full_flow_on_dynamic_pixels_only(built):
    views, _ = _pair_views(built)
    everywhere = pair_losses(views, MatchingConfig(), use_full=True, use_cam=True)
    dynamic_only = pair_losses(views, MatchingConfig(full_flow_dynamic_only=True), use_full=True, use_cam=True)
    for view, all_dir, dyn_dir in zip(views, everywhere.directions, dynamic_only.directions):
        static = (view.extras["reflow_dynamic"][..., 0] / view.alpha[..., 0].clamp_min(1e-6)) < 0.5
        assert dyn_dir.valid.sum() < all_dir.valid.sum() and dyn_dir.valid.any()
        assert not (dyn_dir.valid & static).any()          # no static pixel left in the full-flow terms
        assert torch.equal(dyn_dir.valid, dyn_dir.valid & all_dir.valid)
    assert torch.equal(dynamic_only.losses["cf_mc"], everywhere.losses["cf_mc"])  # camera flow untouched
    # each dynamic pixel keeps the weight it has in the loss over all pixels: sum over dynamic / count of all
    l1_all = pair_losses(views, MatchingConfig(ssim_weight=0.0), use_full=True, use_cam=False)
    l1_dyn = pair_losses(views, MatchingConfig(ssim_weight=0.0, full_flow_dynamic_only=True), use_full=True,
                         use_cam=False)
    expected = []
    for k, (all_dir, dyn_dir) in enumerate(zip(l1_all.directions, l1_dyn.directions)):
        error = (dyn_dir.warped - views[k].camera.image).abs().sum(-1)
        expected.append(error[dyn_dir.valid].sum() / (3 * all_dir.valid.sum()))
    got, want = l1_dyn.losses["ff_mc"].item(), 5.0 * torch.stack(expected).mean().item()
    assert got == pytest.approx(want, rel=1e-5)
    assert not torch.equal(dynamic_only.losses["ff_mc"], everywhere.losses["ff_mc"])
    plugin = ReFlowPlugin({"ReFlowParams": ReFlowParams(full_flow_region="dynamic", pair_mode="both")},
                          enabled=frozenset({"separation", "full_flow"}))
    plugin.scene_depth = 1.0
    ctx = built.ctx
    ctx.stage, ctx.iteration = "fine", 2
    assert plugin.config.full_flow_dynamic_only
    assert set(plugin.extra_features(ctx, 0)) == {"reflow_flow", "reflow_dynamic"}  # the share is rendered


def test_full_flow_min_share_keeps_mixed_edge_pixels_out(built):
    """--full_flow_min_share: only pixels whose rendered dynamic share reaches it carry full flow."""
    views, _ = _pair_views(built)
    half = pair_losses(views, MatchingConfig(full_flow_dynamic_only=True), use_full=True, use_cam=False)
    strict = pair_losses(views, MatchingConfig(full_flow_dynamic_only=True, full_flow_min_share=0.9),
                         use_full=True, use_cam=False)
    mixed_seen = 0
    for view, loose, tight in zip(views, half.directions, strict.directions):
        share = view.extras["reflow_dynamic"][..., 0] / view.alpha[..., 0].clamp_min(1e-6)
        mixed = (share >= 0.5) & (share < 0.9)
        assert torch.equal(tight.valid, loose.valid & (share >= 0.9))
        mixed_seen += int((loose.valid & mixed).sum())
    assert mixed_seen > 0  # the scene has mixed pixels, so the two settings differ
    assert strict.losses["ff_mc"].item() != pytest.approx(half.losses["ff_mc"].item())
    plugin = ReFlowPlugin({"ReFlowParams": ReFlowParams(full_flow_min_share=0.9)})
    assert plugin.config.full_flow_min_share == 0.9


def test_full_flow_share_threshold_is_relative_to_the_views_most_dynamic_pixel(built):
    """A single faint layer of dynamic Gaussians (opacity 0.9, less between keyframes) never reaches a
    share of 0.9: the full-flow gate then takes min_share of the view's top share (at least 0.5), so
    its interior enters and its edge stays out (CMU Panoptic basketball: no pixel at all before);
    where some pixel reaches min_share the gate is min_share itself."""
    share = torch.tensor([[0.2, 0.5, 0.6], [0.7, 0.72, 0.75]])
    usable = torch.ones_like(share, dtype=torch.bool)
    threshold, top = dynamic_threshold(share, usable, 0.9)
    assert top.item() == pytest.approx(0.75) and threshold.item() == pytest.approx(0.675)
    assert dynamic_threshold(share, usable & (share < 0.7), 0.9)[0].item() == pytest.approx(0.54)
    assert dynamic_threshold(share * 0.5, usable, 0.9)[0].item() == pytest.approx(0.5)  # majority-dynamic floor
    assert dynamic_threshold(share / 0.75, usable, 0.9)[0].item() == pytest.approx(0.9)  # dense layers: as before
    assert dynamic_threshold(share / 0.75 * 0.95, usable, 0.9)[0].item() == pytest.approx(0.9)  # some pixel >= 0.9: as before
    assert dynamic_threshold(share, usable, 0.3)[0].item() == pytest.approx(0.3)  # a low min_share as given

    views, _ = _pair_views(built)
    for view in views:  # every dynamic Gaussian at 0.75 of its weight: the top share drops below 0.9
        view.extras["reflow_dynamic"] = view.extras["reflow_dynamic"] * 0.75
    faint = pair_losses(views, MatchingConfig(full_flow_dynamic_only=True, full_flow_min_share=0.9,
                                              full_flow_relative_gate=True), use_full=True, use_cam=False)
    fixed = pair_losses(views, MatchingConfig(full_flow_dynamic_only=True, full_flow_min_share=0.9),
                        use_full=True, use_cam=False)  # the default: the fixed gate
    assert not any(direction.valid.any() for direction in fixed.directions)
    everywhere = pair_losses(views, MatchingConfig(), use_full=True, use_cam=False)
    for k, (view, direction, all_dir) in enumerate(zip(views, faint.directions, everywhere.directions)):
        share = view.extras["reflow_dynamic"][..., 0] / view.alpha[..., 0].clamp_min(1e-6)
        top = share[all_dir.valid].max()
        assert top < 0.9 and not (all_dir.valid & (share >= 0.9)).any()  # the fixed 0.9 gate: nothing
        assert direction.valid.any()
        assert torch.equal(direction.valid, all_dir.valid & (share >= (0.9 * top).clamp(0.5, 0.9)))
        assert faint.metrics[f"flow_top_share_{k}"] == pytest.approx(top.item(), rel=1e-5)
        assert faint.metrics[f"flow_valid_{k}"] > 0
    assert faint.losses["ff_mc"].item() > 0


def test_camera_flow_occlusion_test_drops_inconsistent_pixels(built):
    from reflow_plugin.warp import occlusion_mask

    views, _ = _pair_views(built)
    h, w = views[1].depth.shape[:2]  # an "occluder" in view b: a block much nearer than the scene
    views[1].depth = views[1].depth.clone()
    views[1].depth[h // 4: 3 * h // 4, w // 4: 3 * w // 4] *= 0.3
    plain = pair_losses(views, MatchingConfig(), use_full=False, use_cam=True)
    tested = pair_losses(views, MatchingConfig(cam_occlusion=True), use_full=False, use_cam=True)
    dropped = 0
    for k, (p, t) in enumerate(zip(plain.directions, tested.directions)):
        consistent = occlusion_mask(p.cam_flow, plain.directions[1 - k].cam_flow, 0.01, 0.5)
        assert torch.equal(t.static, p.static & consistent)  # the plain mask, minus the inconsistent pixels
        dropped += int((p.static & ~consistent).sum())
    assert dropped > 0, "the pair's views must disagree somewhere for this test to check anything"
    assert tested.losses["cf_mc"].item() != plain.losses["cf_mc"].item()


def test_skips(built):
    plugin = built.hooks.plugins[0]
    ctx = built.ctx
    cam = built.train_cameras[0]
    assert not plugin._cam_between(cam, cam)  # a pair whose cameras do not move: no camera-flow loss
    assert plugin._cam_between(built.train_cameras[0], built.train_cameras[1])
    views, _ = _pair_views(built, stage="coarse")
    assert "reflow_flow" not in views[0].extras  # no full flow in the coarse stage (paper A.4)
    silent = ReFlowPlugin(enabled=frozenset({"separation"}))
    ctx.views = views
    assert silent.extra_features(ctx, 0) is None and silent.extra_losses(ctx) is None
    assert silent.select_batch(ctx) is None and silent.select_partners(ctx) is None  # the host's own sampling
    every = ReFlowPlugin({"ReFlowParams": ReFlowParams(flow_every=3, pair_mode="both")})  # every third iteration
    every.scene_depth = plugin.scene_depth
    ctx.stage = "fine"
    ctx.iteration = 6
    ctx.batch = [built.train_cameras[0], built.train_cameras[1]]
    assert every._flags(ctx) == ([True, True], [True, True])
    ctx.iteration = 7
    assert every.extra_features(ctx, 0) is None and every.extra_losses(ctx) is None


def test_coarse_stage_freezes_dynamic_gaussians_and_masks_the_loss(built):
    plugin = built.hooks.plugins[0]
    ctx = built.ctx
    views, _ = _pair_views(built, stage="coarse")
    weights = plugin.loss_weights(ctx, 0)
    mask = views[0].camera.mask
    assert torch.equal(weights[..., 0] == 0, mask > 0.5)
    model = ctx.model
    model.optimizer.zero_grad(set_to_none=True)
    torch.stack([v.image.sum() for v in views]).sum().backward()
    plugin.post_backward(ctx)
    dynamic = model.deformation_table
    assert model._xyz.grad[dynamic].abs().sum() == 0 and model._xyz.grad[~dynamic].abs().sum() > 0
    ctx.stage = "fine"
    assert plugin.loss_weights(ctx, 0) is None
    assert torch.equal(plugin.protected_gaussians(ctx), dynamic)


def test_short_run_writes_every_output(tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    trainer = build_trainer(_argv(tiny_scene, out, 10, 30, "--flow_vis_every", "15"))
    result = trainer.train()
    summary = finish_run(trainer, result)
    config = json.loads((out / "config.json").read_text())
    assert config["_components"]["reflow"] == ["cam_flow", "comp_init", "full_flow", "separation"]
    assert config["ReFlowParams"]["lambda_ff"] == 5.0
    results = json.loads((out / "results.json").read_text())
    assert results["reflow"]["mask_source"] == "dataset" and results["reflow"]["labels"]["dynamic"] > 0
    method = f"ours_{result.final_iteration}"
    assert results[method]["PSNR-dynamic"] is not None and results[method]["PSNR-static"] is not None
    flow = json.loads((out / "flow_metrics.json").read_text())[method]
    assert flow["available"] and flow["train"]["pairs"] > 0 and np.isfinite(flow["train"]["epe"])
    assert len(list((out / "reflow" / "flow_vis").glob("*.png"))) == 2
    assert summary.evaluation.mean["PSNR"] > 10
    log = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    losses = {k for r in log if r["kind"] == "iter" for k in r.get("losses", {})}
    assert {"reflow/ff_mc", "reflow/cf_mc"} <= losses, losses
    capsys.readouterr()
    written = render_from_argv(["-m", str(out), "--skip_video"])  # render.py restores the plugin
    assert (written["test"] / "renders" / "00000.png").is_file()
    # render.py's own --quiet decides, not the training run's (trained with --quiet)
    assert "[loaded]" in capsys.readouterr().out
    render_from_argv(["-m", str(out), "--skip_video", "--skip_train", "--quiet"])
    assert "[loaded]" not in capsys.readouterr().out


def test_external_flow_row_trains_and_caches_the_dis_flow(tiny_scene, tmp_path, monkeypatch):
    out = tmp_path / "run"
    trainer = build_trainer(_argv(tiny_scene, out, 2, 6, "--enable", "ext_flow", "--disable", "full_flow"))
    result = trainer.train()
    log = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    losses = {k for r in log if r["kind"] == "iter" for k in r.get("losses", {})}
    assert "reflow/ext" in losses and "reflow/ff_mc" not in losses, losses
    cached = sorted((out / "reflow" / "external_flow").glob("*.npz"))
    assert cached and result.final_iteration == 6
    # a second cache over the same folder reads the files: DIS is never called again
    import reflow_plugin.external as external

    monkeypatch.setattr(external, "flow_pair", lambda *a, **k: pytest.fail("DIS recomputed"))
    cams = {c.image_name: c for c in trainer.train_cameras}
    name_a, name_b = cached[0].stem.split("__")
    flow, ok = external.ExternalFlowCache(out / "reflow" / "external_flow").get(cams[name_a], cams[name_b])
    assert flow.shape == (cams[name_a].height, cams[name_a].width, 2) and ok.dtype == torch.bool


def test_external_flow_loss_is_l1_on_confident_valid_pixels():
    from reflow_plugin.external import external_flow_loss

    flow = torch.zeros(4, 5, 2, requires_grad=True)
    target = torch.ones(4, 5, 2)
    valid = torch.ones(4, 5, dtype=torch.bool)
    confident = torch.zeros(4, 5, dtype=torch.bool)
    confident[0, :2] = True
    target[1:] = 100.0  # outside the confident pixels: must not count
    loss = external_flow_loss(flow, valid, target, confident)
    assert float(loss.detach()) == pytest.approx(1.0)
    loss.backward()
    assert flow.grad[1:].abs().sum() == 0 and flow.grad[0, :2].abs().sum() > 0
    empty = external_flow_loss(flow, valid, target, torch.zeros_like(confident))
    assert float(empty.detach()) == 0.0 and empty.requires_grad


@pytest.mark.parametrize("extent, cap, expected", [
    (0.57, 1.0, 10.0),          # the synthetic scenes (extent < 1): the plain 10x
    (3.4, 1.0, 10.0 / 3.4),     # a large-scale scene: the extent factor undone above the cap
    (3.4, 0.0, 10.0),           # cap 0: 4DGS's extent factor, uncapped
])
def test_dynamic_lr_multiplier_caps_the_extent_factor(extent, cap, expected):
    plugin = ReFlowPlugin({"ReFlowParams": ReFlowParams(dynamic_lr_extent_cap=cap)})
    model = types.SimpleNamespace(spatial_lr_scale=extent)
    assert plugin._dynamic_lr_multiplier(model) == pytest.approx(expected)
    # the effective rate factor of the dynamic branch (extent x multiplier) never exceeds 10 x cap
    if cap:
        assert extent * plugin._dynamic_lr_multiplier(model) <= 10.0 * cap + 1e-9


@pytest.mark.parametrize("extent, flags, expected", [
    (0.6, {}, 1.0),                                  # below the cap: 4DGS's parametrisation
    (36.0, {}, 36.0),                                # scale 50 (truck's extent): deltas x extent / cap
    (36.0, {"dynamic_lr_extent_cap": 4.0}, 9.0),
    (36.0, {"dynamic_lr_extent_cap": 0.0}, 1.0),     # uncapped 4DGS rates: nothing to make up for
])
def test_dynamic_branch_position_scale_follows_the_capped_extent(extent, flags, expected):
    from reflow_plugin.separation import SeparatedDeformation
    from tests._model_helpers import hidden_args

    plugin = ReFlowPlugin({"ReFlowParams": ReFlowParams(**flags)})
    scaled = []
    model = types.SimpleNamespace(spatial_lr_scale=extent, deformation=SeparatedDeformation(hidden_args()),
                                  scale_learning_rate=lambda group, factor: scaled.append((group, factor)))
    plugin._scale_dynamic_branch(model)
    assert model.deformation.deformation_net.position_scale == pytest.approx(expected)
    assert plugin.info["dynamic_position_scale"] == pytest.approx(expected)
    assert [g for g, _ in scaled] == ["deformation", "grid"]


@pytest.mark.parametrize("flow, general, expected", [
    (True, 0.06, (0.02, "the flow provider's limit, FLOW_CLOUD_MAX_DEPTH_ERROR")),  # flow cloud: the tighter limit
    (False, 0.06, (0.06, "--canonical_max_depth_error")),                           # depth prior: the general one
    (True, 0.01, (0.01, "--canonical_max_depth_error")),                            # the smaller of the two applies
    (True, 0.0, (0.02, "the flow provider's limit, FLOW_CLOUD_MAX_DEPTH_ERROR")),   # general off: the flow one holds
])
def test_a_flow_canonical_cloud_must_agree_with_the_sfm_points_more_closely(flow, general, expected):
    from types import SimpleNamespace

    from reflow_plugin.canonical_construction import CanonicalConstruction

    plugin = SimpleNamespace(p=SimpleNamespace(canonical_max_depth_error=general))
    assert CanonicalConstruction.depth_error_limit(plugin, flow) == expected
