"""Clone / split / prune / opacity reset keep every per-Gaussian tensor and Adam state in step;
the 4DGS densification schedule."""

import math

import pytest
import torch

from baselines.fourdgs.densification import densification_step, densification_thresholds
from baselines.fourdgs.gaussian_model import ROW_GROUPS
from tests._model_helpers import make_model, opt_args

COUNT = 10


def _tagged_model():
    """Row i of every per-Gaussian tensor carries the value i; Adam exp_avg row i = 0.1 * (i + 1)."""
    model = make_model(count=COUNT)
    rows = torch.arange(COUNT, dtype=torch.float32)
    with torch.no_grad():
        for attribute in ROW_GROUPS.values():
            param = getattr(model, attribute)
            param.copy_(rows.view(-1, *([1] * (param.dim() - 1))).expand_as(param))
        # Small (cloning candidates); column 0 sets the size, columns 1-2 carry the tag as -20 - i.
        model._scaling[:, 0] = math.log(1e-3)
        model._scaling[:, 1:] = -20.0 - rows[:, None]
    model._deformation_table[::2] = False
    model.register_gaussian_buffer("tag", torch.arange(COUNT))
    model.register_gaussian_parameter("extra", rows[:, None].repeat(1, 2), lr=0.0)
    for group in model.optimizer.param_groups:
        if group["name"] in ROW_GROUPS or group["name"] == "extra":
            param = group["params"][0]
            param.grad = (rows + 1).view(-1, *([1] * (param.dim() - 1))).expand_as(param).clone()
    saved_lrs = [g["lr"] for g in model.optimizer.param_groups]
    for group in model.optimizer.param_groups:
        group["lr"] = 0.0  # moments update, values stay the row tags
    model.optimizer.step()
    for group, lr in zip(model.optimizer.param_groups, saved_lrs):
        group["lr"] = lr
    model.optimizer.zero_grad(set_to_none=True)
    return model


def _row_tags(model):
    """name -> [N] tag read from each per-Gaussian tensor (first element of each row)."""
    tags = {name: getattr(model, attr).detach().reshape(model.num_gaussians, -1)[:, 0]
            for name, attr in ROW_GROUPS.items()}
    tags["scaling"] = -20.0 - model._scaling.detach()[:, 1]
    tags["extra"] = model.registered_parameters["extra"].detach()[:, 0]
    tags["tag"] = model.registered_buffers["tag"].float()
    return tags


def _moment_tags(model):
    """name -> [N] tag recovered from exp_avg (0.1 * (tag + 1)), NaN-free; 0 moment -> -1."""
    out = {}
    for group in model.optimizer.param_groups:
        if group["name"] in ROW_GROUPS or group["name"] == "extra":
            param = group["params"][0]
            exp_avg = model.optimizer.state[param]["exp_avg"].reshape(param.shape[0], -1)[:, 0]
            out[group["name"]] = exp_avg / 0.1 - 1
    return out


def test_prune_keeps_rows_and_adam_state_aligned():
    model = _tagged_model()
    table_before = model._deformation_table.clone()
    mask = torch.zeros(COUNT, dtype=torch.bool)
    mask[[1, 4, 7]] = True
    model.prune_points(mask)
    survivors = torch.tensor([0, 2, 3, 5, 6, 8, 9], dtype=torch.float32)
    for name, tags in _row_tags(model).items():
        torch.testing.assert_close(tags, survivors, msg=name)
    for name, tags in _moment_tags(model).items():
        torch.testing.assert_close(tags, survivors, msg=name)
    assert torch.equal(model._deformation_table, table_before[~mask])
    assert model.max_radii2D.shape == (7,) and model.denom.shape == (7, 1) and model._deformation_accum.shape == (7, 3)
    assert model.optimizer.state[model._xyz]["step"].item() == 1.0


def test_clone_appends_copies_of_parents_with_fresh_moments():
    model = _tagged_model()
    table_before = model._deformation_table.clone()
    grads = torch.zeros(COUNT, 1)
    grads[[2, 5]] = 1.0
    model.xyz_gradient_accum += 3.0
    added = model.densify_and_clone(grads, grad_threshold=0.5, scene_extent=10.0)
    assert added == 2 and model.num_gaussians == COUNT + 2
    expected = torch.cat([torch.arange(COUNT, dtype=torch.float32), torch.tensor([2.0, 5.0])])
    for name, tags in _row_tags(model).items():
        torch.testing.assert_close(tags, expected, msg=name)
    for name, tags in _moment_tags(model).items():
        torch.testing.assert_close(tags[:COUNT], expected[:COUNT], msg=name)
        torch.testing.assert_close(tags[COUNT:], torch.tensor([-1.0, -1.0]), msg=name)  # zero moments
    assert torch.equal(model._deformation_table, torch.cat([table_before, table_before[[2, 5]]]))
    assert not model.xyz_gradient_accum.any()  # 4DGS resets the statistics after densifying


def test_split_replaces_parents_by_two_smaller_children():
    model = _tagged_model()
    with torch.no_grad():
        model._scaling[[3, 8], 0] = math.log(0.5)  # large enough to split
    grads = torch.zeros(COUNT, 1)
    grads[[3, 8, 4]] = 1.0  # row 4 is small: not split
    torch.manual_seed(0)
    split = model.densify_and_split(grads, grad_threshold=0.5, scene_extent=10.0)
    assert split == 2 and model.num_gaussians == COUNT - 2 + 4
    survivors = [0, 1, 2, 4, 5, 6, 7, 9]
    children = [3, 8, 3, 8]  # 4DGS tiles the selection N times
    expected = torch.tensor(survivors + children, dtype=torch.float32)
    tags = _row_tags(model)
    for name in ("f_dc", "f_rest", "opacity", "rotation", "extra", "tag"):
        torch.testing.assert_close(tags[name], expected, msg=name)
    torch.testing.assert_close(tags["xyz"][:8], expected[:8])
    torch.testing.assert_close(tags["scaling"][:8], expected[:8])
    offsets = model._xyz.detach()[8:] - torch.tensor(children, dtype=torch.float32)[:, None]
    assert offsets.abs().max() < 0.5 * 6 and offsets.abs().max() > 0  # sampled around the parent
    parent_scaling = torch.tensor([[math.log(0.5), -23.0, -23.0], [math.log(0.5), -28.0, -28.0]]).repeat(2, 1)
    torch.testing.assert_close(model._scaling.detach()[8:], parent_scaling - math.log(1.6))
    for name, moment_tags in _moment_tags(model).items():
        torch.testing.assert_close(moment_tags[:8], expected[:8], msg=name)
        torch.testing.assert_close(moment_tags[8:], torch.full((4,), -1.0), msg=name)


def test_densify_uses_mean_gradient_and_reports_counts():
    model = _tagged_model()
    model.percent_dense = 0.01
    with torch.no_grad():
        model._scaling[6, 0] = math.log(0.5)
    model.xyz_gradient_accum[[1, 6]] = 4.0
    model.denom[[1, 6]] = 2.0  # mean 2.0
    model.xyz_gradient_accum[2] = 4.0
    model.denom[2] = 8.0  # mean 0.5: below threshold
    cloned, split = model.densify(max_grad=1.0, extent=10.0)
    assert (cloned, split) == (1, 1)
    assert model.registered_buffers["tag"].tolist()[-3:] == [1, 6, 6]


def test_prune_rules_and_opacity_reset():
    model = _tagged_model()
    with torch.no_grad():
        model._opacity.copy_(torch.logit(torch.linspace(0.001, 0.5, COUNT))[:, None])
        model._scaling[9, 0] = math.log(2.0)  # > 0.1 * extent
    model.max_radii2D[5] = 30.0
    assert model.prune(min_opacity=0.05, extent=10.0, max_screen_size=None) == 1  # only opacity 0.001
    tags = model.registered_buffers["tag"].tolist()
    assert tags == [1, 2, 3, 4, 5, 6, 7, 8, 9]
    assert model.prune(min_opacity=0.05, extent=10.0, max_screen_size=20) == 2  # screen (5) and world (9)
    assert model.registered_buffers["tag"].tolist() == [1, 2, 3, 4, 6, 7, 8]

    opacity_param = model._opacity
    step_before = model.optimizer.state[opacity_param]["step"].clone()
    xyz_moments = model.optimizer.state[model._xyz]["exp_avg"].clone()
    model.reset_opacity()
    opacities = model.get_opacity.detach().squeeze(1)
    assert opacities.max() <= 0.01 + 1e-7
    state = model.optimizer.state[model._opacity]
    assert not state["exp_avg"].any() and not state["exp_avg_sq"].any()
    assert torch.equal(state["step"], step_before)
    assert torch.equal(model.optimizer.state[model._xyz]["exp_avg"], xyz_moments)


def test_schedule_follows_4dgs_conditions():
    opt = opt_args(densify_from_iter=2, densification_interval=3, pruning_from_iter=2, pruning_interval=4,
                   opacity_reset_interval=5, densify_until_iter=20)
    model = make_model(count=30)
    ran = {}
    for iteration in range(1, 22):
        count = model.num_gaussians
        record = densification_step(
            model, opt, iteration, "coarse", cameras_extent=100.0,
            visible=torch.ones(count, dtype=torch.bool), radii=torch.zeros(count),
            means2d_grad=torch.zeros(count, 2), width=64, height=48, prune_min_gaussians=0,
        )
        ran[iteration] = (record.densify_ran, record.prune_ran, record.opacity_reset, record.stats_updated)
    assert [i for i, r in ran.items() if r[0]] == [3, 6, 9, 12, 15, 18]
    assert [i for i, r in ran.items() if r[1]] == [4, 8, 12, 16]
    assert [i for i, r in ran.items() if r[2]] == [5, 10, 15]
    assert [i for i, r in ran.items() if r[3]] == list(range(1, 20))

    big = make_model(count=30)
    record = densification_step(big, opt, 12, "coarse", 100.0, torch.ones(30, dtype=torch.bool), torch.zeros(30),
                                torch.zeros(30, 2), 64, 48, max_gaussians=30, prune_min_gaussians=30)
    assert not record.densify_ran and not record.prune_ran  # 360k cap / 200k floor (scaled down)


def test_screen_size_pruning_starts_after_first_opacity_reset():
    opt = opt_args(pruning_from_iter=2, pruning_interval=4, opacity_reset_interval=5, densify_until_iter=20,
                   densification_interval=1000)
    model = make_model(count=30)
    radii = torch.zeros(30)
    radii[0] = 30.0
    visible = torch.ones(30, dtype=torch.bool)
    args = dict(cameras_extent=100.0, visible=visible, radii=radii, means2d_grad=torch.zeros(30, 2), width=64,
                height=48, prune_min_gaussians=0)
    assert densification_step(model, opt, 4, "fine", **args).pruned == 0
    assert densification_step(model, opt, 8, "fine", **args).pruned == 1


def test_stats_use_visible_rows_and_stop_at_densify_until():
    opt = opt_args(densify_until_iter=10)
    model = make_model(count=4)
    visible = torch.tensor([True, False, True, True])
    grads = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 2.0], [0.0, 0.0]])
    densification_step(model, opt, 3, "fine", 1.0, visible, torch.tensor([3.0, 9.0, 1.0, 0.0]), grads, 10, 20)
    torch.testing.assert_close(model.xyz_gradient_accum.squeeze(1), torch.tensor([5.0, 0.0, 20.0, 0.0]))
    torch.testing.assert_close(model.max_radii2D, torch.tensor([3.0, 0.0, 1.0, 0.0]))
    record = densification_step(model, opt, 10, "fine", 1.0, visible, torch.ones(4), grads, 10, 20)
    assert not record.stats_updated
    torch.testing.assert_close(model.denom.squeeze(1), torch.tensor([1.0, 0.0, 1.0, 1.0]))


def test_fine_thresholds_interpolate_towards_after_values():
    opt = opt_args(densify_grad_threshold_fine_init=0.0004, densify_grad_threshold_after=0.0002,
                   opacity_threshold_fine_init=0.01, opacity_threshold_fine_after=0.005, densify_until_iter=1000)
    assert densification_thresholds(opt, 500, "fine") == pytest.approx((0.0003, 0.0075))
    assert densification_thresholds(opt, 500, "coarse") == (opt.densify_grad_threshold_coarse,
                                                              opt.opacity_threshold_coarse)
