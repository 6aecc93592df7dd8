"""Flow matching ALONE teaches motion: a raw shift, and the dynamic branch of the separated model.

A textured carpet of Gaussians faces a fixed camera; frame b shows it shifted by a known number
of pixels. Only L_mc (the warp of I_b by the rendered full flow against I_a) is minimised, so any
recovered motion comes from flow matching. These are small versions of what the embedded scene
measures (docs/REFLOW.md, "The failure ReFlow must fix").
"""
from __future__ import annotations

import math

import numpy as np
import torch

from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.render import composite, project_gaussians
from reflow_plugin.flow import flow_features, full_flow
from reflow_plugin.separation import TIME_CENTER, TIME_LOG_SCALE, SeparatedDeformation
from reflow_plugin.warp import backward_warp, gaussian_blur, photometric_loss
from tests._model_helpers import hidden_args, opt_args
from tests.raster_cases import intrinsics

WIDTH, HEIGHT, DEPTH = 40, 32, 4.0
K = intrinsics(WIDTH, HEIGHT, focal=32.0)
PIXEL = DEPTH / float(K[0, 0])  # world units per pixel at the carpet's depth


def _carpet(rows: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """(means [rows^2, 3] on a plane at DEPTH overfilling the image, colours [rows^2, 3])."""
    torch.manual_seed(0)
    u, v = torch.meshgrid(torch.linspace(-4, WIDTH + 4, rows), torch.linspace(-4, HEIGHT + 4, rows), indexing="xy")
    means = torch.stack([(u - K[0, 2]) / K[0, 0] * DEPTH, (v - K[1, 2]) / K[1, 1] * DEPTH,
                         torch.full_like(u, DEPTH)], -1).reshape(-1, 3)
    return means, torch.rand(means.shape[0], 3)


def _project(means, quats, scales, opacities):
    return project_gaussians(means, quats, scales, torch.eye(4), K, WIDTH, HEIGHT, opacities=opacities, backend="cpu")


def _warp_loss(proj_a, proj_b, opacities, image_a, image_b, sigmas=(0.0,)) -> torch.Tensor:
    """L_mc of direction a -> b averaged over blur levels (sigma 0 = full resolution).

    reflow_plugin.matching uses (0, *flow_blur_sigmas).
    """
    maps, _, alpha = composite(proj_a, opacities, flow_features(proj_a, proj_b), WIDTH, HEIGHT, backend="cpu")
    flow, valid = full_flow(maps, alpha, 0.5)
    terms = []
    for sigma in sigmas:
        a, b = (image_a, image_b) if not sigma else (gaussian_blur(image_a, sigma), gaussian_blur(image_b, sigma))
        warped, inside = backward_warp(b, flow)
        terms.append(photometric_loss(warped, a, valid & inside))
    return torch.stack(terms).mean()


def _shift_fit(shift_px: float, sigmas: tuple[float, ...], steps: int = 80) -> torch.Tensor:
    """Remaining error (x, y) in pixels of a raw shift of the carpet after `steps` Adam steps of L_mc."""
    means, colours = _carpet()
    n = means.shape[0]
    scales = torch.tensor([[0.09, 0.09, 0.01]]).repeat(n, 1)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    opac = torch.full((n,), 0.95)
    true = torch.tensor([shift_px, -0.5 * shift_px, 0.0]) * PIXEL
    images = [composite(_project(m, quats, scales, opac), opac, colours, WIDTH, HEIGHT, backend="cpu")[0]
              for m in (means, means + true)]
    proj_a = _project(means, quats, scales, opac)
    shift = torch.zeros(3, requires_grad=True)
    optimizer = torch.optim.Adam([shift], lr=0.1 * PIXEL)
    for _ in range(steps):
        loss = _warp_loss(proj_a, _project(means + shift, quats, scales, opac), opac, *images, sigmas=sigmas)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return (shift.detach()[:2] - true[:2]) / PIXEL


def test_flow_matching_alone_recovers_a_shift_and_blur_widens_its_range():
    assert _shift_fit(2.0, (0.0,)).abs().max() < 0.1
    # the photometric capture range is about the texture's scale: 7 px is out of it at full
    # resolution, and inside it on blurred images
    assert _shift_fit(7.0, (0.0,)).abs().max() > 2.0
    assert _shift_fit(7.0, (3.0,)).abs().max() < 0.5


def _anchored_carpet_model(anchored: bool) -> GaussianModel:
    """All-dynamic separated model of the carpet, every Gaussian seeded at t = 0."""
    means, colours = _carpet(rows=24)
    torch.manual_seed(0)
    means[:, 2] += 0.01 * torch.rand(means.shape[0])  # the host sizes the planes from the cloud's box
    model = GaussianModel(0, hidden_args(), deformation=SeparatedDeformation(hidden_args(), anchored=anchored))
    model.create_from_pcd(means.numpy(), colours.numpy(), spatial_lr_scale=1.0)
    with torch.no_grad():
        model._opacity.fill_(math.log(0.95 / 0.05))
        model._scaling.copy_(torch.log(torch.tensor([0.11, 0.11, 0.01])).expand_as(model._scaling))
    model.set_deformation_table(torch.ones(model.num_gaussians, dtype=torch.bool))
    model.register_gaussian_buffer(TIME_CENTER, torch.zeros(model.num_gaussians, 1))
    model.training_setup(opt_args())
    model.deformation.fit_box(model.get_xyz.detach(), 0.2)
    return model


def test_flow_matching_alone_teaches_the_dynamic_branch_a_motion():
    """Keyframe seeds (anchored) learn a 5 px motion from L_mc alone and stay put at their own time."""
    model = _anchored_carpet_model(anchored=True)
    canonical = model.get_xyz.detach().clone()
    true = torch.tensor([5.0, 2.0, 0.0]) * PIXEL
    t_b = 0.1
    state = model.deform(0.0, "fine")
    image_a = composite(_project(state.means, state.quats, state.scales, state.opacities), state.opacities,
                        state.shs[:, 0].detach(), WIDTH, HEIGHT, backend="cpu")[0].detach()
    image_b = composite(_project(state.means + true, state.quats, state.scales, state.opacities), state.opacities,
                        state.shs[:, 0].detach(), WIDTH, HEIGHT, backend="cpu")[0].detach()
    model.freeze(["xyz", "f_dc", "f_rest", "opacity", "scaling", "rotation"])
    for group in ("deformation", "grid"):
        model.scale_learning_rate(group, 10.0)

    def motion_error() -> float:
        with torch.no_grad():
            moved = model.deform(t_b, "fine").means - canonical
        return float(((moved - true)[:, :2] / PIXEL).norm(dim=1).median())

    before = motion_error()
    for iteration in range(1, 121):
        model.update_learning_rate(iteration)
        a, b = model.deform(0.0, "fine"), model.deform(t_b, "fine")
        proj_a = _project(a.means, a.quats, a.scales, a.opacities)
        proj_b = _project(b.means, b.quats, b.scales, b.opacities)
        loss = _warp_loss(proj_a, proj_b, a.opacities, image_a, image_b, sigmas=(0.0, 2.0, 4.0))
        model.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        model.optimizer.step()
    after = motion_error()
    assert before > 5.0 and after < 1.0, (before, after)
    with torch.no_grad():  # anchored: the seeds have not moved at their own time
        torch.testing.assert_close(model.deform(0.0, "fine").means, canonical, atol=1e-6, rtol=0)


def test_anchor_is_what_keeps_seeds_at_their_keyframe():
    """With random (trained-looking) heads, anchored seeds sit at their canonical place at t = center."""
    for anchored in (True, False):
        model = _anchored_carpet_model(anchored)
        with torch.no_grad():
            for p in model.deformation.parameters():
                p.add_(0.1 * torch.randn_like(p))
            centers = torch.linspace(-0.5, 0.5, model.num_gaussians).unsqueeze(1)
            model.pop_gaussian_buffer(TIME_CENTER)
            model.register_gaussian_buffer(TIME_CENTER, centers)
            at_own_time = model.deform(centers, "fine").means
            elsewhere = model.deform(centers + 0.3, "fine").means
        offset = (at_own_time - model.get_xyz).norm(dim=1).max()
        assert (offset < 1e-6) == anchored, (anchored, float(offset))
        assert (elsewhere - model.get_xyz).norm(dim=1).max() > 1e-3
    assert np.isfinite(float(offset.detach()))


def test_deform_many_keeps_keyframe_windows_and_anchors_of_every_time():
    """The separated model deformed at a view's and a partner's time in ONE call (the trainer's
    prepare_views) equals two calls: per-row times, temporal windows, anchors, culling, labels."""
    model = _anchored_carpet_model(anchored=True)
    model.deformation.window_cull = 1e-3
    n = model.num_gaussians
    with torch.no_grad():
        for p in model.deformation.parameters():
            p.add_(0.1 * torch.randn_like(p))
        model.pop_gaussian_buffer(TIME_CENTER)
        model.register_gaussian_buffer(TIME_CENTER, torch.linspace(-0.5, 0.5, n).unsqueeze(1))
    model.register_gaussian_buffer(TIME_LOG_SCALE, torch.full((n, 1), math.log(0.1)))
    table = torch.ones(n, dtype=torch.bool)
    table[::3] = False  # a third static
    model.set_deformation_table(table)
    times = (-0.4, 0.3)
    many = model.deform_many(times, "fine")
    for got, t in zip(many, times):
        expected = model.deform(t, "fine")
        for field in ("means", "log_scales", "rotations", "opacity_logits"):
            torch.testing.assert_close(getattr(got, field), getattr(expected, field), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(many[0].means[~table], model.get_xyz[~table])  # static rows untouched
    # SH is no head of the network: every time shares the canonical tensor (no copy, no scatter)
    assert many[0].shs is many[1].shs
    torch.testing.assert_close(many[0].shs, model.deform(times[0], "fine").shs)
    assert (many[0].opacity_logits != many[1].opacity_logits).any()  # windows depend on the time


def test_deform_many_evaluates_each_gaussians_anchor_once_with_the_same_values_and_gradients():
    """D(x, 0) of a Gaussian deformed at two times is computed once (M + U network rows, not 2M);
    values and parameter gradients equal two separate calls."""
    model = _anchored_carpet_model(anchored=True)
    n = model.num_gaussians
    model.deformation.double()  # float64: D(x, t) - D(x, 0) cancels, float32 rounding would dominate
    for name in ("_xyz", "_scaling", "_rotation", "_opacity", "_features_dc", "_features_rest"):
        getattr(model, name).data = getattr(model, name).data.double()
    with torch.no_grad():
        for p in model.deformation.parameters():
            p.add_(0.1 * torch.randn_like(p))
    rows_seen: list[int] = []
    model.deformation.deformation_net.register_forward_hook(lambda m, inputs, out: rows_seen.append(len(inputs[1])))
    times = (-0.4, 0.3)
    wrt = [model._xyz, *(p for p in model.deformation.parameters() if p.requires_grad)]
    many = model.deform_many(times, "fine")
    assert rows_seen == [2 * n + n]  # every Gaussian at both times, its anchor once
    loss_many = sum((s.means.square().sum() + s.log_scales.sum() + s.rotations.sum()) for s in many)
    grads_many = torch.autograd.grad(loss_many, wrt, allow_unused=True)
    singles = [model.deform(t, "fine") for t in times]
    assert rows_seen[1:] == [2 * n, 2 * n]  # a single time: nothing to share
    for got, expected in zip(many, singles):
        for field in ("means", "log_scales", "rotations"):
            torch.testing.assert_close(getattr(got, field), getattr(expected, field), atol=1e-12, rtol=1e-10)
    loss_single = sum((s.means.square().sum() + s.log_scales.sum() + s.rotations.sum()) for s in singles)
    grads_single = torch.autograd.grad(loss_single, wrt, allow_unused=True)
    for got, expected in zip(grads_many, grads_single):
        if expected is None:
            assert got is None or not got.any()
        else:
            torch.testing.assert_close(got, expected, atol=1e-10, rtol=1e-8)


def test_partner_rows_leave_what_the_view_cannot_show_undeformed_with_equal_flow_values_and_gradients():
    """The trainer deforms a partner only for the Gaussians its batch view can show
    (ReFlowPlugin.partner_rows -> SeparatedDeformation.alive_at -> deform_many's rows): the view's
    composited flow channels towards the partner, and every gradient through them, equal those of
    the partner deformed whole, in float64; the skipped rows are left canonical."""
    model = _anchored_carpet_model(anchored=True)
    model.deformation.window_cull = 1e-3  # ReFlow's WINDOW_CULL
    model.deformation.double()
    for name in ("_xyz", "_scaling", "_rotation", "_opacity", "_features_dc", "_features_rest"):
        getattr(model, name).data = getattr(model, name).data.double()
    n = model.num_gaussians
    with torch.no_grad():
        for p in model.deformation.parameters():
            p.add_(0.1 * torch.randn_like(p))
        model.pop_gaussian_buffer(TIME_CENTER)
        # keyframe copies at three times: at t_a = 0 the ones centred at 0.6 are culled, at t_b = 0.3 not
        model.register_gaussian_buffer(TIME_CENTER, torch.tensor([-0.3, 0.0, 0.6]).repeat(n // 3 + 1)[:n]
                                       .unsqueeze(1).double())
    model.register_gaussian_buffer(TIME_LOG_SCALE, torch.full((n, 1), math.log(0.12), dtype=torch.float64))
    t_a, t_b = 0.0, 0.3
    buffers = model.deformation_inputs()
    shown = model.deformation.alive_at(t_a, buffers)
    deformed_at_b = model.deformation.alive_at(t_b, buffers)
    skipped = deformed_at_b & ~shown
    assert int(skipped.sum()) > n // 10 and bool(shown.any())
    wrt = [model._xyz, model._scaling, model._rotation, model._opacity,
           *(p for p in model.deformation.parameters() if p.requires_grad)]

    def flow_and_grads(rows):
        view, partner = model.deform_many((t_a, t_b), "fine", rows)
        def project(s):
            return project_gaussians(s.means, s.quats, s.scales, torch.eye(4, dtype=torch.float64), K.double(),
                                     WIDTH, HEIGHT, opacities=s.opacities, backend="cpu")

        proj_a, proj_b = project(view), project(partner)
        maps, _, alpha = composite(proj_a, view.opacities, flow_features(proj_a, proj_b), WIDTH, HEIGHT, backend="cpu")
        weights = torch.linspace(0.5, 1.5, 7, dtype=maps.dtype)  # every channel, A and c and validity
        loss = (maps * weights).sum() + alpha.sum()
        grads = torch.autograd.grad(loss, wrt, allow_unused=True)
        return maps.detach(), grads, partner

    whole_maps, whole_grads, _ = flow_and_grads(None)
    maps, grads, partner = flow_and_grads([None, shown])
    assert whole_maps.abs().sum() > 0
    torch.testing.assert_close(maps, whole_maps, rtol=1e-12, atol=1e-12)
    scale = max(float(g.abs().max()) for g in whole_grads if g is not None)
    for got, expected in zip(grads, whole_grads):
        if expected is None:
            assert got is None or not got.any()
        else:
            # summation order: the network's batch has fewer rows (entries near zero differ by ~1e-12)
            torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10 * scale)
    torch.testing.assert_close(partner.means[skipped], model.get_xyz.detach()[skipped], rtol=0, atol=0)
    # a mask that drops a row the view shows changes the channels (the comparison can fail)
    wrong = shown.clone()
    wrong[(shown & deformed_at_b & model.deformation_table).nonzero()[:20, 0]] = False
    assert not torch.allclose(flow_and_grads([None, wrong])[0], whole_maps, rtol=1e-12, atol=1e-12)


def test_alive_at_claims_nothing_when_the_cull_could_leave_a_gaussian_visible():
    model = _anchored_carpet_model(anchored=True)
    model.register_gaussian_buffer(TIME_LOG_SCALE, torch.full((model.num_gaussians, 1), math.log(0.1)))
    buffers = model.deformation_inputs()
    model.deformation.window_cull = 1e-3
    assert model.deformation.alive_at(0.9, buffers) is not None and not model.deformation.alive_at(0.9, buffers).any()
    model.deformation.window_cull = 0.01  # above 1/255: a culled Gaussian may still be drawn
    assert model.deformation.alive_at(0.9, buffers) is None


def test_partner_rows_follow_the_view_of_each_partner_and_the_switch(monkeypatch):
    """ReFlowPlugin.partner_rows: one mask per projected partner, the Gaussians alive at the time of
    the batch view that partner belongs to; REFLOW4DGS_PARTNER_ROWS=0 asks for whole partners."""
    from types import SimpleNamespace

    from reflow_plugin.plugin import PARTNER_ROWS_SWITCH, ReFlowPlugin

    model = _anchored_carpet_model(anchored=True)
    model.deformation.window_cull = 1e-3
    n = model.num_gaussians
    model.pop_gaussian_buffer(TIME_CENTER)
    model.register_gaussian_buffer(TIME_CENTER, torch.tensor([-0.5, 0.5]).repeat(n // 2 + 1)[:n].unsqueeze(1))
    model.register_gaussian_buffer(TIME_LOG_SCALE, torch.full((n, 1), math.log(0.1)))
    plugin = ReFlowPlugin()
    views = [SimpleNamespace(time=-0.5), SimpleNamespace(time=0.1), SimpleNamespace(time=0.5)]
    plugin._partner_cameras = [SimpleNamespace(time=0.0), None, SimpleNamespace(time=0.0)]  # nothing alive at 0
    plugin._partners_projected = True
    ctx = SimpleNamespace(model=model, batch=views)
    early, late = plugin.partner_rows(ctx)  # the views at -0.5 and 0.5 (the one at 0.1 has no partner)
    centres = model.deformation_inputs()[TIME_CENTER][:, 0]
    assert torch.equal(early, centres == -0.5) and torch.equal(late, centres == 0.5)
    monkeypatch.setenv(PARTNER_ROWS_SWITCH, "0")
    assert plugin.partner_rows(ctx) is None
