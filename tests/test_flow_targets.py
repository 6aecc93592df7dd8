"""Flow targets that must not exist (issue 25, items 14 and 15).

14: on the gsplat backend a Gaussian culled from view b (outside the image, too faint) carries the
    principal point as its mean and an identity covariance; read as a flow target it would send
    view a's pixels to the image centre. Tested on the CPU with gsplat's stand-ins applied to the
    torch projection (`culled_standins`, the function the gsplat backend itself uses).
15: in the coarse stage the dynamic Gaussians are hidden, so the rendered dynamic-ness channel
    calls every pixel static; camera-flow matching must still leave the moving object's pixels out.
"""
from __future__ import annotations

import torch

from baselines.render import Projection, composite, project_gaussians
from baselines.render.gsplat_backend import culled_standins
from reflow_plugin.flow import flow_features, full_flow, pixel_grid
from tests.raster_cases import intrinsics

W, H = 24, 20


def _as_gsplat(projection: Projection, K: torch.Tensor) -> Projection:
    means2d, conics, cov2d = culled_standins(projection.means2d, projection.conics, projection.visible, K)
    return Projection(means2d=means2d, cov2d=cov2d, conics=conics, depths=projection.depths,
                      radii=projection.radii, visible=projection.visible)


def _leaving_scene():
    """Two Gaussians at z = 4: one stays near the centre, one near the right edge leaves the image in b."""
    K = intrinsics(W, H, focal=20.0)
    z = 4.0

    def at(px: float, py: float) -> list[float]:
        return [(px - float(K[0, 2])) / float(K[0, 0]) * z, (py - float(K[1, 2])) / float(K[1, 1]) * z, z]

    means_a = torch.tensor([at(6.0, 10.0), at(20.0, 10.0)])
    means_b = torch.tensor([at(7.0, 10.0), at(60.0, 10.0)])  # the second one is 36 px right of the image
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)
    scales = torch.full((2, 3), 0.35)
    opacities = torch.tensor([0.95, 0.95])
    return K, means_a, means_b, quats, scales, opacities


def test_gaussians_culled_in_view_b_are_no_flow_target():
    K, means_a, means_b, quats, scales, opacities = _leaving_scene()
    eye = torch.eye(4)
    proj_a = project_gaussians(means_a, quats, scales, eye, K, W, H, opacities=opacities, backend="reference")
    proj_b = project_gaussians(means_b, quats, scales, eye, K, W, H, opacities=opacities, backend="reference")
    assert proj_a.visible.all() and proj_b.visible.tolist() == [True, False]

    results = {}
    for name, pb in (("torch", proj_b), ("gsplat", _as_gsplat(proj_b, K))):
        features = flow_features(proj_a, pb)
        assert features[1, 6] == 0 and features[0, 6] == 1  # the culled Gaussian is not a valid target
        maps, _, alpha = composite(proj_a, opacities, features, W, H, backend="reference")
        results[name] = full_flow(maps, alpha, 0.5)

    flow, valid = results["gsplat"]
    # the leaving Gaussian's pixels (around x = 20) are invalid, not sent to the principal point
    assert not valid[8:13, 18:23].any()
    targets = pixel_grid(H, W, flow) + flow
    centre = torch.stack([K[0, 2], K[1, 2]])
    near_centre = (targets - centre).norm(dim=-1) < 3.0
    assert not (valid & near_centre & (pixel_grid(H, W, flow)[..., 0] > 15)).any()
    # the staying Gaussian still has its flow (1 px to the right)
    assert valid[10, 6] and abs(float(flow[10, 6, 0]) - 1.0) < 0.05
    # both backends' conventions give the same flow and validity
    torch.testing.assert_close(results["torch"][0], flow)
    assert torch.equal(results["torch"][1], valid)


def _coarse_camera_flow_step(scene, out):
    """One coarse iteration of ReFlow with camera flow on; returns (trainer, plugin)."""
    from baselines.fourdgs.app import build_trainer
    from tests.test_trainer import base_argv

    trainer = build_trainer(base_argv(scene, out, 5, 5, "--plugin", "reflow", "--disable", "comp_init,full_flow",
                                      "--cam_flow_min_motion", "0"))
    trainer.build()
    trainer._begin_stage("coarse", 5)
    plugin = trainer.hooks.plugins[0]
    assert plugin._hides_dynamic(trainer.ctx), "the coarse stage hides the dynamic Gaussians"
    trainer.ctx.iteration = 1
    trainer.train_step()
    return trainer, plugin


def test_coarse_camera_flow_leaves_the_moving_object_out(tiny_scene, tmp_path):
    trainer, plugin = _coarse_camera_flow_step(tiny_scene, tmp_path / "run")
    views = trainer.ctx.views
    assert plugin._last is not None and "cf_mc" in plugin._last.losses
    for k, direction in enumerate(plugin._last.directions):
        moving = views[k].camera.mask > 0.5
        assert moving.any(), "the tiny balloon scene has a moving object in every frame"
        assert direction.static.any()
        assert not (direction.static & moving).any(), "moving-object pixels counted as static"
        # and none of the kept pixels samples the moving object in the other view
        other = views[1 - k].camera.mask.unsqueeze(-1)
        from reflow_plugin.warp import backward_warp
        landed, _ = backward_warp(other, direction.cam_flow)
        assert (landed[..., 0][direction.static] < 1e-6).all()
    trainer.run_log.close()
