"""Host extensions made for plugins: pruning protection, baseline-loss weights, deformation inputs,
per-row gradient freezing, dynamic-region metrics, run facts in config.json."""
from __future__ import annotations

import json

import pytest
import torch

from arguments import parse_train_args, write_cfg_args
from baselines.fourdgs.densification import densification_step
from baselines.fourdgs.evaluate import region_metrics
from baselines.fourdgs.hooks import HookRunner
from baselines.fourdgs.plugins import Plugin
from baselines.metrics import psnr
from tests._model_helpers import make_model, opt_args


def _transparent_model(count=30):
    model = make_model(count)
    with torch.no_grad():
        model._opacity.fill_(-10.0)  # every Gaussian below any opacity threshold
    return model


def _densify(model, protect, **opt):
    n = model.num_gaussians
    return densification_step(
        model, opt_args(densify_from_iter=0, pruning_from_iter=0, densification_interval=1, pruning_interval=1,
                        densify_until_iter=100, **opt),
        1, "coarse", 2.0, torch.ones(n, dtype=torch.bool), torch.ones(n), torch.zeros(n, 2), 64, 64,
        prune_min_gaussians=0, protect=protect)


def test_protected_gaussians_are_not_pruned():
    model = _transparent_model()
    protect = torch.zeros(30, dtype=torch.bool)
    protect[:10] = True
    kept_xyz = model.get_xyz.detach()[:10].clone()
    record = _densify(model, protect)
    assert record.prune_ran and record.pruned == 20
    torch.testing.assert_close(model.get_xyz.detach(), kept_xyz)
    with pytest.raises(ValueError, match="protect"):
        _densify(model, torch.zeros(3, dtype=torch.bool))


def test_clones_of_protected_gaussians_are_protected():
    model = _transparent_model(20)
    protect = torch.zeros(20, dtype=torch.bool)
    protect[:5] = True
    model.percent_dense = 10.0  # all small: densify clones every Gaussian with a large gradient
    n = model.num_gaussians
    record = densification_step(
        model, opt_args(densify_from_iter=0, pruning_from_iter=0, densification_interval=1, pruning_interval=1,
                        densify_until_iter=100, densify_grad_threshold_coarse=1e-9),
        1, "coarse", 2.0, torch.ones(n, dtype=torch.bool), torch.ones(n), torch.ones(n, 2), 64, 64,
        prune_min_gaussians=0, protect=protect)
    assert record.cloned == 20 and model.num_gaussians == 10  # 5 protected + their 5 clones
    assert "_protect" not in model.registered_buffers


class _Weights(Plugin):
    name = "weights_test"

    def __init__(self, value) -> None:
        super().__init__()
        self.value = value

    def loss_weights(self, ctx, view_index):
        return None if self.value is None else self.value.clone()

    def protected_gaussians(self, ctx):
        return None if self.value is None else torch.tensor([True, False])


def test_hook_runner_combines_masks_and_weights():
    ones = torch.ones(2, 2, 1)
    runner = HookRunner([_Weights(ones * 0.5), _Weights(None), _Weights(ones * 0.5)])
    torch.testing.assert_close(runner.product("loss_weights", None, 0), ones * 0.25)
    assert runner.combined_mask("protected_gaussians", None).tolist() == [True, False]
    assert HookRunner([_Weights(None)]).product("loss_weights", None, 0) is None


def test_weighted_baseline_loss(tiny_scene, tmp_path):
    from baselines.fourdgs.app import REPO_ROOT, build_trainer

    argv = ["-s", str(tiny_scene), "-m", str(tmp_path / "run"), "--quiet", "--lambda_dssim", "0.2",
            "--configs", str(REPO_ROOT / "arguments/synthetic/default.py")]
    trainer = build_trainer(argv)
    trainer.build()
    trainer._begin_stage("coarse", 1)
    ctx = trainer.ctx
    ctx.batch = trainer.train_cameras[:2]
    from baselines.fourdgs.renderer import composite_view, prepare_view
    ctx.views = [composite_view(prepare_view(ctx.model, c, "coarse"), ctx.background) for c in ctx.batch]
    plain = trainer.baseline_losses()
    h, w = ctx.views[0].image.shape[:2]
    trainer.hooks = HookRunner([_Weights(torch.ones(h, w, 1))])
    same = trainer.baseline_losses()
    for key in ("l1", "dssim"):
        torch.testing.assert_close(same[key], plain[key])
    half = torch.ones(h, w, 1)
    half[:, : w // 2] = 0
    trainer.hooks = HookRunner([_Weights(half)])
    weighted = trainer.baseline_losses()
    renders = torch.stack([v.image for v in ctx.views])[:, :, w // 2:]
    gts = torch.stack([v.camera.image for v in ctx.views])[:, :, w // 2:]
    torch.testing.assert_close(weighted["l1"], (renders - gts).abs().mean())


def test_deformation_inputs_and_reserved_names():
    model = make_model(10)
    model.set_deformation_table(torch.arange(10) < 3)
    inputs = model.deformation_inputs()
    assert inputs["deformation_table"].tolist() == [True] * 3 + [False] * 7
    with pytest.raises(ValueError, match="already exists"):
        model.register_gaussian_buffer("deformation_table", torch.zeros(10))
    with pytest.raises(ValueError, match="set_deformation_table"):
        model.set_deformation_table(torch.ones(4, dtype=torch.bool))


def test_zero_row_gradients():
    model = make_model(8)
    model._xyz.sum().backward()
    rows = torch.zeros(8, dtype=torch.bool)
    rows[2] = True
    model.zero_row_gradients(rows)
    assert model._xyz.grad[2].abs().sum() == 0 and model._xyz.grad[3].abs().sum() > 0


def test_region_metrics():
    gt = torch.zeros(4, 6, 3)
    image = gt.clone()
    mask = torch.zeros(4, 6)
    mask[:, :2] = 1
    image[:, :2] = 0.1  # error only inside the mask
    out = region_metrics(image, gt, mask)
    assert out["PSNR-dynamic"] == pytest.approx(20.0, abs=1e-4)
    assert out["PSNR-static"] == float("inf") or out["PSNR-static"] > 90
    assert out["SSIM-static"] > out["SSIM-dynamic"]
    empty = region_metrics(image, gt, torch.zeros(4, 6))
    assert empty["PSNR-dynamic"] is None and empty["PSNR-static"] == pytest.approx(float(psnr(image, gt)))


def test_config_json_records_facts(tmp_path):
    args = parse_train_args(["-s", "x"])
    _, path = write_cfg_args(tmp_path, args, {"_components": {"reflow": ["full_flow"]}})
    assert json.loads(path.read_text())["_components"] == {"reflow": ["full_flow"]}
    with pytest.raises(ValueError, match="must start with"):
        write_cfg_args(tmp_path, args, {"components": {}})


class _Partner(Plugin):
    """Asks for the next training camera as a partner of the batch's view and records what it saw."""

    name = "partner"

    def select_partners(self, ctx):
        self.batch = list(ctx.batch)
        index = next(i for i, c in enumerate(ctx.train_cameras) if c is ctx.batch[0])
        return [ctx.train_cameras[(index + 1) % len(ctx.train_cameras)]]

    def extra_losses(self, ctx):
        self.partners, self.views = list(ctx.partners), list(ctx.views)
        return None


def _fine_trainer(tiny_scene, tmp_path):
    """A built trainer on the tiny scene with the synthetic config, in its fine stage."""
    from baselines.fourdgs.app import REPO_ROOT, build_trainer

    argv = ["-s", str(tiny_scene), "-m", str(tmp_path / "run"), "--quiet",
            "--configs", str(REPO_ROOT / "arguments/synthetic/default.py")]
    trainer = build_trainer(argv)
    trainer.build()
    trainer._begin_stage("fine", 2)
    return trainer


def test_partners_are_projected_not_rendered_and_stay_out_of_the_loss(tiny_scene, tmp_path):
    trainer = _fine_trainer(tiny_scene, tmp_path)
    plugin = _Partner()
    trainer.hooks = HookRunner([plugin])
    trainer.ctx.iteration = 1
    trainer.train_step()
    ctx = trainer.ctx
    assert len(plugin.views) == 1 and len(plugin.partners) == 1  # batch_size 1: one rendered view
    partner = plugin.partners[0]
    assert partner.image is None and partner.colors is None  # projected only
    assert partner.projection.means2d.shape[0] == ctx.model.num_gaussians
    assert partner.camera is not plugin.views[0].camera
    view = plugin.views[0]
    expected = (view.image - view.camera.image).abs().mean()
    torch.testing.assert_close(ctx.losses["l1"].detach(), expected.detach())  # the partner adds no loss


class _SharedPartner(_Partner):
    """A partner whose odd rows take the batch view's state (partner_shared_rows), or a bad answer."""

    name = "shared_partner"

    def __init__(self, answer=None):
        self.answer = answer

    def partner_shared_rows(self, ctx):
        if self.answer is not None:
            return self.answer
        return [(0, torch.arange(ctx.model.num_gaussians) % 2 == 1)]


def test_partner_shared_rows_give_the_partner_the_views_state_and_bad_answers_are_named(tiny_scene, tmp_path):
    from baselines.fourdgs.plugins import PluginError

    trainer = _fine_trainer(tiny_scene, tmp_path)
    with torch.no_grad():  # time-dependent deformation, so the two times differ
        for p in trainer.ctx.model.deformation.parameters():
            p.add_(0.05 * torch.randn_like(p))
    plugin = _SharedPartner()
    trainer.hooks = HookRunner([plugin])
    trainer.ctx.iteration = 1
    trainer.train_step()
    assert len(plugin.views) == 1, len(plugin.views)
    view, partner = plugin.views[0].state, plugin.partners[0].state
    odd = torch.arange(view.num_gaussians) % 2 == 1
    assert plugin.views[0].camera.time != plugin.partners[0].camera.time
    torch.testing.assert_close(partner.means[odd], view.means[odd])
    assert not torch.allclose(partner.means[~odd], view.means[~odd])  # the others at the partner's own time
    for bad in ([(1, odd)], [(0, odd), None]):
        trainer.hooks = HookRunner([_SharedPartner(bad)])
        with pytest.raises(PluginError, match="partner_shared_rows"):
            trainer.train_step()
    trainer.run_log.close()


def test_non_finite_plugin_channel_is_named_with_its_count(tiny_scene, tmp_path):
    """The rasterizer only knows "features"; composite_view names the block (a plugin's channel
    or the colours) and how many Gaussians carry NaN/inf."""
    from baselines.fourdgs.app import build_trainer
    from baselines.fourdgs.renderer import composite_view, prepare_view
    from tests.test_trainer import base_argv

    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "run", 1, 1))
    trainer.build()
    trainer._begin_stage("coarse", 1)
    ctx = trainer.ctx
    view = prepare_view(ctx.model, trainer.train_cameras[0], "coarse")
    channel = torch.zeros(view.colors.shape[0], 2)
    channel[[3, 7], 1] = float("nan")
    with pytest.raises(ValueError, match=r"'my_flow' in 2 Gaussian\(s\) \(of \d+\)") as info:
        composite_view(view, ctx.background, {"fine": torch.zeros(view.colors.shape[0], 1), "my_flow": channel})
    assert "'fine'" not in str(info.value) and "'colours'" not in str(info.value)
    assert trainer.train_cameras[0].image_name in str(info.value)
    trainer.run_log.close()
