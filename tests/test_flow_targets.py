"""Flow targets that must not exist (issue 25, items 14 and 15).

14: on the gsplat backend a Gaussian culled from view b (outside the image, too faint) came with
    the principal point as its mean and an identity covariance (gsplat leaves culled entries
    uninitialised); read as a flow target it sent view a's pixels to the image centre, marked valid.
    The backend now fills culled entries with the torch projection's values (`fill_culled`), so the
    flow is the CPU's. Tested on the CPU: gsplat's raw output is mimicked (uninitialised = NaN).
15: in the coarse stage the dynamic Gaussians are hidden, so the rendered dynamic-ness channel
    calls every pixel static; camera-flow matching must still leave the moving object's pixels out.
"""
from __future__ import annotations

import pytest
import torch

from baselines.render import Projection, composite, project_gaussians
from baselines.render.gsplat_backend import fill_culled
from reflow_plugin.flow import flow_features, full_flow, pixel_grid
from tests.raster_cases import intrinsics

W, H = 24, 20


def _gsplat_like(truth: Projection, means, quats, scales, K) -> Projection:
    """What project_gaussians_gsplat returns: gsplat's values where visible (here the torch ones),
    uninitialised memory (NaN) where culled, then the backend's fill."""
    culled = ~truth.visible[:, None]
    raw_means = torch.where(culled, torch.full_like(truth.means2d, float("nan")), truth.means2d)
    raw_conics = torch.where(culled, torch.full_like(truth.conics, float("nan")), truth.conics)
    means2d, conics, cov2d = fill_culled(raw_means, raw_conics, truth.visible, means, quats, scales, torch.eye(4), K,
                                         W, H)
    return Projection(means2d=means2d, cov2d=cov2d, conics=conics, depths=truth.depths, radii=truth.radii,
                      visible=truth.visible)


def _leaving_scene():
    """Three Gaussians at z = 4: one stays, one leaves the image in view b, one fades out in view b."""
    K = intrinsics(W, H, focal=20.0)
    z = 4.0

    def at(px: float, py: float) -> list[float]:
        return [(px - float(K[0, 2])) / float(K[0, 0]) * z, (py - float(K[1, 2])) / float(K[1, 1]) * z, z]

    means_a = torch.tensor([at(6.0, 10.0), at(20.0, 10.0), at(12.0, 4.0)])
    means_b = torch.tensor([at(7.0, 10.0), at(60.0, 10.0), at(13.0, 4.0)])  # #2 ends 36 px right of the image
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3)
    scales = torch.full((3, 3), 0.35)
    opacity_a = torch.tensor([0.95, 0.95, 0.95])
    opacity_b = torch.tensor([0.95, 0.95, 1e-4])  # #3 fades out (a temporal opacity window)
    return K, means_a, means_b, quats, scales, opacity_a, opacity_b


def test_gaussians_culled_in_view_b_flow_to_where_they_are():
    K, means_a, means_b, quats, scales, opacity_a, opacity_b = _leaving_scene()
    eye = torch.eye(4)
    proj_a = project_gaussians(means_a, quats, scales, eye, K, W, H, opacities=opacity_a, backend="reference")
    proj_b = project_gaussians(means_b, quats, scales, eye, K, W, H, opacities=opacity_b, backend="reference")
    assert proj_a.visible.all() and proj_b.visible.tolist() == [True, False, False]
    gsplat_b = _gsplat_like(proj_b, means_b, quats, scales, K)
    torch.testing.assert_close(gsplat_b.means2d, proj_b.means2d)
    torch.testing.assert_close(gsplat_b.cov2d, proj_b.cov2d)

    flows = {}
    for name, pb in (("torch", proj_b), ("gsplat", gsplat_b)):
        maps, _, alpha = composite(proj_a, opacity_a, flow_features(proj_a, pb), W, H, backend="reference")
        flows[name] = full_flow(maps, alpha, 0.5)
    flow, valid = flows["gsplat"]
    torch.testing.assert_close(flow, flows["torch"][0])
    assert torch.equal(valid, flows["torch"][1])
    targets = pixel_grid(H, W, flow) + flow
    # the leaving Gaussian's pixels flow 40 px right, off the image: not to the principal point
    assert valid[10, 20] and abs(float(flow[10, 20, 0]) - 40.0) < 0.5
    centre = torch.stack([K[0, 2], K[1, 2]])
    assert not (valid[8:13, 18:23] & ((targets[8:13, 18:23] - centre).norm(dim=-1) < 3.0)).any()
    # the faded one still has its target (1 px right), the staying one too
    assert valid[4, 12] and abs(float(flow[4, 12, 0]) - 1.0) < 0.05
    assert valid[10, 6] and abs(float(flow[10, 6, 0]) - 1.0) < 0.05


def _coarse_camera_flow_step(scene, out, pair_mode="both"):
    """One coarse iteration of ReFlow with camera flow on; returns (trainer, plugin)."""
    from baselines.fourdgs.app import build_trainer
    from tests.test_trainer import base_argv

    trainer = build_trainer(base_argv(scene, out, 5, 5, "--plugin", "reflow", "--disable", "comp_init,full_flow",
                                      "--cam_flow_min_motion", "0", "--pair_mode", pair_mode))
    trainer.build()
    trainer._begin_stage("coarse", 5)
    plugin = trainer.hooks.plugins[0]
    assert plugin._hides_dynamic(trainer.ctx), "the coarse stage hides the dynamic Gaussians"
    trainer.ctx.iteration = 1
    trainer.train_step()
    return trainer, plugin


@pytest.mark.parametrize("pair_mode", ["both", "partner"])
def test_coarse_camera_flow_leaves_the_moving_object_out(tiny_scene, tmp_path, pair_mode):
    from reflow_plugin.warp import backward_warp

    trainer, plugin = _coarse_camera_flow_step(tiny_scene, tmp_path / "run", pair_mode)
    assert plugin._last is not None
    result, pairs = plugin._last
    assert "cf_mc" in result.losses and len(result.directions) == len(pairs) >= 1
    for direction, pair in zip(result.directions, pairs):
        target = pair.target
        moving = pair.source.camera.mask > 0.5
        assert moving.any(), "the tiny balloon scene has a moving object in every frame"
        assert direction.static.any()
        assert not (direction.static & moving).any(), "moving-object pixels counted as static"
        # and none of the kept pixels samples the moving object in the other frame
        landed, _ = backward_warp(target.mask.unsqueeze(-1), direction.cam_flow)
        assert (landed[..., 0][direction.static] < 1e-6).all()
    trainer.run_log.close()
