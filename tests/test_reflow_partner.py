"""ReFlow's `pair_mode partner` (one rendered view, a projected partner frame) and the flow-target options."""
from __future__ import annotations

import pytest
import torch

from baselines.fourdgs.app import build_trainer
from baselines.fourdgs.renderer import composite_view, prepare_view
from baselines.synthetic import get_scene, simulate
from reflow_plugin.matching import DYNAMIC_KEY, FLOW_KEY, FlowPair, MatchingConfig, flow_losses
from tests.test_reflow_plugin import _argv


@pytest.fixture(scope="module")
def partner_run(tiny_scene, tmp_path_factory):
    """A trainer (default pair_mode partner) at the start of its fine stage."""
    trainer = build_trainer(_argv(tiny_scene, tmp_path_factory.mktemp("partner") / "run", 2, 4))
    trainer.build()
    trainer._begin_stage("fine", 4)
    return trainer


def _step_capturing(trainer) -> tuple[list, list]:
    """One fine training step; returns (composited views, projected partners) with the partners'
    projected means keeping their gradient."""
    plugin, ctx = trainer.hooks.plugins[0], trainer.ctx
    captured = {}
    original = plugin.extra_losses

    def spy(ctx_):
        captured["partners"] = list(ctx_.partners)
        captured["views"] = list(ctx_.views)
        for view in ctx_.partners:
            view.state.means.retain_grad()
        return original(ctx_)

    plugin.extra_losses = spy
    try:
        ctx.iteration = 1
        trainer.train_step()
    finally:
        plugin.extra_losses = original
    return captured["views"], captured["partners"]


def test_partner_step_renders_one_view_and_moves_the_partners_gaussians(partner_run):
    trainer, ctx = partner_run, partner_run.ctx
    plugin = trainer.hooks.plugins[0]
    assert plugin.select_batch(ctx) is None  # the host's own single-view sampling, as the baseline's
    module, calls = ctx.model.deformation, []
    module.forward = lambda *args, **kwargs: calls.append(args[0].num_gaussians) or type(module).forward(
        module, *args, **kwargs)
    try:
        views, partners = _step_capturing(trainer)
    finally:
        del module.forward
    # the view and its partner frame are deformed in ONE call on the rows repeated (prepare_views)
    assert calls == [2 * ctx.model.num_gaussians], calls
    assert len(views) == 1 and len(partners) == 1  # one composited view, one projected partner
    a, b = views[0].camera, partners[0].camera
    order = plugin.sampler.position
    index = {c.uid: i for i, c in enumerate(trainer.train_cameras)}
    assert 1 <= abs(order[index[a.uid]] - order[index[b.uid]]) <= plugin.p.pair_window
    assert partners[0].image is None  # never composited
    assert FLOW_KEY in views[0].extras
    assert {"reflow/ff_mc", "reflow/cf_mc"} <= set(ctx.losses) and "reflow/ff_cr" not in ctx.losses  # no render of b
    dynamic = ctx.model.deformation_table
    grad = partners[0].state.means.grad
    assert grad is not None and grad[dynamic].abs().sum() > 0  # L_mc moves the Gaussians at t_b


def test_partner_frame_gradient_reaches_static_and_dynamic_gaussians(tiny_scene, tmp_path):
    """The partner frame is only projected: its Gaussians' positions reach the losses through their
    flow channels, and both the dynamic and the static ones get a gradient (the paper's)."""
    trainer = build_trainer(_argv(tiny_scene, tmp_path / "run", 2, 4))
    trainer.build()
    trainer._begin_stage("fine", 4)
    _, partners = _step_capturing(trainer)
    grad, dynamic = partners[0].state.means.grad, trainer.ctx.model.deformation_table
    assert grad[dynamic].abs().sum() > 0
    assert grad[~dynamic].abs().sum() > 0


def test_target_side_static_mask_drops_pixels_landing_on_the_moving_object(partner_run):
    ctx = partner_run.ctx
    cams = partner_run.train_cameras
    view = prepare_view(ctx.model, cams[0], "fine")
    features = {DYNAMIC_KEY: ctx.model.deformation_table.float().unsqueeze(1)}
    composite_view(view, ctx.background, features)
    target = cams[2]
    h, w = view.alpha.shape[:2]
    moving = torch.zeros(h, w)
    moving[:, : w // 2] = 1.0  # b's left half "moves"
    plain = flow_losses([FlowPair(view, target)], MatchingConfig(), [False], [True])
    masked = flow_losses([FlowPair(view, target, target_dynamic=moving)], MatchingConfig(), [False], [True])
    flow = plain.directions[0].cam_flow
    lands_x = (torch.arange(w).float() + 0.5).unsqueeze(0) + flow[..., 0]
    on_moving = lands_x < w // 2 - 1  # clearly inside the "moving" half (bilinear edge excluded)
    kept = masked.directions[0].static
    assert not (kept & on_moving).any()
    assert torch.equal(kept, kept & plain.directions[0].static) and kept.sum() < plain.directions[0].static.sum()
    assert set(plain.losses) == {"cf_mc"}  # no render of b: no cross-time term


def test_static_scene_has_no_dynamic_branch_and_no_full_flow(tmp_path):
    scene = simulate(get_scene("static", frames=8, width=24, height=24, seed=0), tmp_path / "static", progress=False)
    trainer = build_trainer(_argv(scene, tmp_path / "run", 2, 3))
    result = trainer.train()
    assert result.final_iteration == 3
    model = trainer.ctx.model
    assert not bool(model.deformation_table.any())
    import json

    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    losses = {k for r in log if r["kind"] == "iter" for k in r.get("losses", {})}
    assert not any(k.startswith("reflow/ff") for k in losses), losses


def test_window_cull_renders_exactly_what_deforming_every_copy_renders(partner_run):
    from baselines.fourdgs.renderer import render

    ctx = partner_run.ctx
    deformation = ctx.model.deformation
    assert deformation.window_cull == pytest.approx(1e-3)  # the default
    camera = partner_run.train_cameras[3]
    from reflow_plugin.separation import TIME_CENTER, TIME_LOG_SCALE

    model = ctx.model
    dynamic = model.deformation_table.nonzero().squeeze(1)
    times = torch.full((model.num_gaussians, 1), float(camera.time))
    buffers = model.gaussian_buffers
    alive = deformation._inside_windows(dynamic, times, buffers[TIME_CENTER], buffers[TIME_LOG_SCALE].detach())
    assert 0 < len(alive) < len(dynamic)  # some copies are culled at this time, some are not
    with torch.no_grad():
        culled = render(ctx.model, camera, "fine", ctx.background)
        deformation.window_cull = 0.0
        try:
            every = render(ctx.model, camera, "fine", ctx.background)
        finally:
            deformation.window_cull = 1e-3
    torch.testing.assert_close(culled.image, every.image, atol=1e-6, rtol=0)
    torch.testing.assert_close(culled.alpha, every.alpha, atol=1e-6, rtol=0)
