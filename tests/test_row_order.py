"""The Gaussians' rows in spatial order (baselines/fourdgs/row_order.py): a layout that changes no result."""
from __future__ import annotations

import pytest
import torch

from baselines.fourdgs import row_order
from baselines.fourdgs.app import build_trainer
from baselines.fourdgs.renderer import render
from baselines.fourdgs.row_order import ENV_SWITCH, morton_codes, spatial_order
from tests._model_helpers import make_model
from tests.test_trainer import base_argv


def test_morton_codes_interleave_x_y_z_bits():
    corners = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    x_bits = sum(1 << (3 * i) for i in range(10))  # all ten x bits set: every third bit from bit 0
    assert morton_codes(corners).tolist() == [0, x_bits, x_bits << 1, x_bits << 2, (1 << 30) - 1]


def test_spatial_order_of_a_shuffled_grid_is_the_z_curve():
    grid = torch.stack(torch.meshgrid(*[torch.arange(2.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    shuffled = grid[torch.randperm(8, generator=torch.Generator().manual_seed(0))]
    ordered = shuffled[spatial_order(shuffled)]
    expected = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]]
    assert ordered.tolist() == expected


def test_sorted_rows_are_close_in_space():
    generator = torch.Generator().manual_seed(1)
    centers = torch.rand(50, 3, generator=generator) * 10
    points = centers[torch.randint(0, 50, (5000,), generator=generator)] + 0.1 * torch.randn(5000, 3, generator=generator)
    step = lambda p: (p[1:] - p[:-1]).norm(dim=1).mean()  # noqa: E731
    assert step(points[spatial_order(points)]) < 0.1 * step(points)


def test_codes_are_defined_for_non_finite_far_and_degenerate_points():
    points = torch.tensor([[float("nan"), 0, 0], [float("inf"), 1, 1], [1e30, 0.5, 0.5], [0.2, 0.5, 0.5],
                           [0.4, 0.5, 0.5]])
    codes = morton_codes(points)
    assert codes.dtype == torch.int64 and bool(((codes >= 0) & (codes < (1 << 30))).all())
    flat = torch.zeros(6, 3)  # every point at one place: one cell, the order unchanged
    assert spatial_order(flat).tolist() == list(range(6))
    assert morton_codes(torch.zeros(0, 3)).shape == (0,)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        morton_codes(torch.zeros(4, 2))


def _row_state(model) -> dict[str, torch.Tensor]:
    """Every per-row tensor of the model, and the Adam moments of its per-row groups."""
    rows = {name: model._get_row_param(name).detach().clone() for name in model._row_param_names()}
    for name in model._row_param_names():
        for key, value in model.optimizer.state[model._get_row_param(name)].items():
            if torch.is_tensor(value) and value.dim() > 0:
                rows[f"adam.{name}.{key}"] = value.clone()
    rows.update(table=model.deformation_table.clone(), accum=model.xyz_gradient_accum.clone(),
                denom=model.denom.clone(), radii=model.max_radii2D.clone(), deformation_accum=model._deformation_accum.clone(),
                buffer=model.registered_buffers["tag"].clone())
    return rows


def test_permute_rows_moves_every_parameter_moment_statistic_and_buffer_together():
    model = make_model(count=30)
    model.register_gaussian_buffer("tag", torch.arange(30.0).unsqueeze(1))
    model.set_deformation_table(torch.arange(30) % 3 == 0)
    model.xyz_gradient_accum = torch.rand(30, 1)
    model.denom = torch.rand(30, 1)
    model.max_radii2D = torch.rand(30)
    for name in model._row_param_names():  # one Adam step: non-zero moments
        param = model._get_row_param(name)
        param.grad = torch.randn_like(param)
    model.optimizer.step()
    before = _row_state(model)
    order = torch.randperm(30, generator=torch.Generator().manual_seed(2))
    model.permute_rows(order)
    after = _row_state(model)
    assert before.keys() == after.keys()
    for key in before:
        torch.testing.assert_close(after[key], before[key][order], rtol=0, atol=0, msg=key)


@pytest.mark.parametrize("order, message", [
    (torch.tensor([0, 0, 1, 2, 3]), "not a permutation"),
    (torch.tensor([0, 1, 2, 3, 5]), "not a permutation"),
    (torch.tensor([0, 1, 2, -1, 4]), "not a permutation"),
    (torch.tensor([0, 1, 2, 3]), r"int64 \[5\]"),
    (torch.tensor([0.0, 1, 2, 3, 4]), r"int64 \[5\]"),
])
def test_permute_rows_refuses_what_is_not_a_permutation(order, message):
    model = make_model(count=5)
    with pytest.raises(ValueError, match=message):
        model.permute_rows(order)


def test_a_permuted_model_renders_the_same_image_and_gradients(tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_SWITCH, "0")
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "run", 1, 1))
    trainer.build()
    model, camera = trainer.ctx.model, trainer.test_cameras[0]
    model.training_setup(trainer.opt)

    def image_and_grads():
        view = render(model, camera, "fine", trainer.ctx.background, "cpu")
        (view.image * torch.linspace(0, 1, view.image.numel()).reshape(view.image.shape)).sum().backward()
        grads = {name: model._get_row_param(name).grad.clone() for name in ("xyz", "opacity", "scaling")}
        return view.image.detach(), grads

    image, grads = image_and_grads()
    order = torch.randperm(model.num_gaussians, generator=torch.Generator().manual_seed(3))
    model.permute_rows(order)
    image2, grads2 = image_and_grads()
    torch.testing.assert_close(image2, image, rtol=1e-5, atol=1e-6)
    for name in grads:
        torch.testing.assert_close(grads2[name], grads[name][order], rtol=1e-4, atol=1e-7, msg=name)


def _sorted(model) -> bool:
    codes = morton_codes(model.get_xyz)
    return bool((codes[1:] >= codes[:-1]).all())


def test_the_trainer_orders_the_rows_at_creation_and_after_each_densification(tiny_scene, tmp_path, monkeypatch):
    from baselines.fourdgs import trainer as trainer_module

    ordered: list[tuple[int, bool]] = []  # (iteration, rows sorted right after) per call
    rewritten: list[int] = []  # iterations whose densification step rewrote the rows
    order_rows, densification_step = row_order.order_rows, trainer_module.densification_step

    def recording_order(model):
        done = order_rows(model)
        ordered.append((trainer.ctx.iteration, _sorted(model)))
        return done

    def recording_step(model, *args, **kwargs):
        record = densification_step(model, *args, **kwargs)
        if record.densify_ran or record.prune_ran:
            rewritten.append(record.iteration)
        return record

    monkeypatch.setattr(trainer_module, "order_rows", recording_order)
    monkeypatch.setattr(trainer_module, "densification_step", recording_step)
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "run", 40, 0))
    trainer.build()
    assert len(ordered) == 1 and ordered[0][1], "the rows must be in spatial order once the model is created"
    assert not _initial_order_kept(trainer)
    trainer.train()
    assert len(rewritten) >= 2
    assert [iteration for iteration, _ in ordered[1:]] == rewritten
    assert all(is_sorted for _, is_sorted in ordered)


def _initial_order_kept(trainer) -> bool:
    """Whether the model's rows are still in the initial cloud's order."""
    cloud = torch.as_tensor(trainer.ctx.point_cloud.points, dtype=torch.float32)
    return torch.equal(trainer.ctx.model.get_xyz.detach(), cloud)


def test_the_switch_keeps_the_order_the_run_makes(tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_SWITCH, "0")
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "run", 1, 1))
    trainer.build()
    assert _initial_order_kept(trainer)
