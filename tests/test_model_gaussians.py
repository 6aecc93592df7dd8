"""GaussianModel: 4DGS initialisation, optimizer groups, schedules, deform, freeze, snapshots."""

import copy
import math

import numpy as np
import pytest
import torch

from baselines.fourdgs.gaussian_model import GROUP_ORDER, SH_C0, GaussianModel
from baselines.fourdgs.lr_schedule import get_expon_lr_func
from tests._model_helpers import hidden_args, make_model, opt_args


def test_create_from_pcd_follows_4dgs_init():
    rng = np.random.default_rng(3)
    points = rng.uniform(-2, 2, (30, 3))
    points[7] = points[3]  # duplicate: zero distance, clamped at 1e-7
    points[8] = points[3]
    points[9] = points[3]
    colors = rng.uniform(0, 1, (30, 3))
    model = GaussianModel(2, hidden_args())
    model.create_from_pcd(points, colors, spatial_lr_scale=5.0)

    squared = ((points[:, None] - points[None]) ** 2).sum(-1)
    np.fill_diagonal(squared, np.inf)
    dist2 = np.maximum(np.sort(squared, axis=1)[:, :3].mean(1), 1e-7)
    expected_log_scale = np.log(np.sqrt(dist2))
    np.testing.assert_allclose(model._scaling.detach().numpy(), np.repeat(expected_log_scale[:, None], 3, 1),
                               rtol=1e-5, atol=1e-6)
    assert model._scaling[3, 0].item() == pytest.approx(math.log(math.sqrt(1e-7)), rel=1e-5)
    assert torch.equal(model._rotation.detach(), torch.tensor([[1.0, 0, 0, 0]]).expand(30, 4))
    torch.testing.assert_close(model.get_opacity.detach(), torch.full((30, 1), 0.1))
    expected_dc = torch.tensor((colors - 0.5) / SH_C0, dtype=torch.float32)
    torch.testing.assert_close(model._features_dc.detach()[:, 0], expected_dc)
    assert model._features_rest.shape == (30, 8, 3) and not model._features_rest.detach().any()
    assert model._deformation_table.dtype == torch.bool and model._deformation_table.all()
    xyz_max, xyz_min = model.get_aabb
    torch.testing.assert_close(xyz_max, torch.tensor(points.max(0), dtype=torch.float32))
    torch.testing.assert_close(xyz_min, torch.tensor(points.min(0), dtype=torch.float32))
    assert model.spatial_lr_scale == 5.0 and model.active_sh_degree == 0


def test_create_from_pcd_rejects_bad_clouds():
    model = GaussianModel(3, hidden_args())
    with pytest.raises(ValueError, match="NaN"):
        model.create_from_pcd(np.array([[0.0, 0, 0], [np.nan, 1, 1]]), np.zeros((2, 3)), 1.0)
    with pytest.raises(ValueError, match="colors"):
        model.create_from_pcd(np.zeros((4, 3)), np.zeros((3, 3)), 1.0)


def test_training_setup_groups_and_schedules():
    model = make_model()
    opt = opt_args()
    groups = {g["name"]: g for g in model.optimizer.param_groups}
    assert [g["name"] for g in model.optimizer.param_groups] == list(GROUP_ORDER)
    assert model.optimizer.defaults["eps"] == 1e-15
    scale = model.spatial_lr_scale
    assert groups["xyz"]["lr"] == pytest.approx(opt.position_lr_init * scale)
    assert groups["deformation"]["lr"] == pytest.approx(opt.deformation_lr_init * scale)
    assert groups["grid"]["lr"] == pytest.approx(opt.grid_lr_init * scale)
    assert groups["f_rest"]["lr"] == pytest.approx(opt.feature_lr / 20)
    assert groups["opacity"]["lr"] == opt.opacity_lr and groups["rotation"]["lr"] == opt.rotation_lr

    rates = model.update_learning_rate(opt.position_lr_max_steps)
    assert rates["xyz"] == pytest.approx(opt.position_lr_final * scale)
    assert rates["grid"] == pytest.approx(opt.grid_lr_final * scale)
    half = model.update_learning_rate(opt.position_lr_max_steps // 2)["deformation"]
    geometric_mean = math.sqrt(opt.deformation_lr_init * opt.deformation_lr_final) * scale
    assert half == pytest.approx(geometric_mean)
    assert groups["deformation"]["lr"] == half and groups["f_dc"]["lr"] == opt.feature_lr


def test_expon_schedule_delay_and_errors():
    schedule = get_expon_lr_func(1e-2, 1e-4, lr_delay_steps=100, lr_delay_mult=0.1, max_steps=1000)
    assert schedule(0) == pytest.approx(1e-3)  # delayed start: lr_init * delay_mult
    assert schedule(100) == pytest.approx(1e-2 * (1e-2) ** 0.1)
    assert schedule(5000) == pytest.approx(1e-4)
    assert schedule(-1) == 0.0
    assert get_expon_lr_func(0.0, 0.0)(10) == 0.0
    with pytest.raises(ValueError, match="lr_final"):
        get_expon_lr_func(1e-3, 0.0)


def model_with_time_dependent_planes() -> GaussianModel:
    """make_model() with its HexPlane cells drawn so that time changes the deformation."""
    model = make_model()
    with torch.no_grad():
        for level in model.deformation.deformation_net.grid.grids:
            for plane in level:
                plane.uniform_(0.5, 1.5)
    return model


def test_deform_coarse_is_canonical_and_fine_moves():
    model = model_with_time_dependent_planes()
    coarse = model.deform(0.5, "coarse")
    assert coarse.means is model._xyz and coarse.log_scales is model._scaling
    assert coarse.shs.shape == (40, 16, 3)
    fine_a = model.deform(0.2, "fine")
    fine_b = model.deform(torch.tensor(0.9), "fine")
    assert not torch.allclose(fine_a.means, fine_b.means)
    per_gaussian = model.deform(torch.full((40,), 0.2), "fine")
    torch.testing.assert_close(per_gaussian.means, fine_a.means)
    with pytest.raises(ValueError, match="stage"):
        model.deform(0.1, "medium")


def test_times_outside_the_span_extrapolate_hold_or_move_on_linearly():
    model = model_with_time_dependent_planes()
    at = {t: model.deform(t, "fine") for t in (0.0, 0.1, 0.2, 0.8, 0.95)}  # no span: the field as it is
    model.set_time_span((0.1, 0.8), "extrapolate")
    torch.testing.assert_close(model.deform(0.0, "fine").means, at[0.0].means)
    model.set_time_span((0.1, 0.8), "hold")
    torch.testing.assert_close(model.deform(0.0, "fine").means, at[0.1].means)
    torch.testing.assert_close(model.deform(torch.tensor(0.95), "fine").means, at[0.8].means)
    torch.testing.assert_close(model.deform(0.5, "fine").means, model.deform(torch.tensor(0.5), "fine").means)
    assert not torch.allclose(at[0.0].means, at[0.1].means)  # holding changes something here
    model.set_time_span((0.1, 0.8), "linear")
    linear = model.deform(0.0, "fine")  # 0.1 before the span: mirror time 0.2
    torch.testing.assert_close(linear.means, 2 * at[0.1].means - at[0.2].means)
    torch.testing.assert_close(linear.log_scales, at[0.1].log_scales)  # the shape is held
    times = torch.tensor([0.0, 0.5] * 20)  # per-Gaussian times, one by one
    mixed = model.deform(times, "fine").means
    torch.testing.assert_close(mixed[0::2], linear.means[0::2])
    torch.testing.assert_close(mixed[1::2], model.deform(0.5, "fine").means[1::2])
    with pytest.raises(ValueError, match="mode"):
        model.set_time_span((0.1, 0.8), "clamp")
    for bad in ((0.5, 0.2), (float("nan"), 1.0)):
        with pytest.raises(ValueError, match="set_time_span"):
            model.set_time_span(bad)


def _assert_states_close(got, expected) -> None:
    for field in ("means", "log_scales", "rotations", "opacity_logits", "shs"):
        torch.testing.assert_close(getattr(got, field), getattr(expected, field), atol=1e-5, rtol=1e-5)


def test_deform_many_equals_one_deform_per_time_values_and_gradients():
    """One deformation call for several times gives each time's Gaussians and the same gradients."""
    times = (0.2, 0.9, 0.2)
    model = model_with_time_dependent_planes()
    model.training_setup(opt_args())
    many = model.deform_many(times, "fine")
    one_by_one = [model.deform(t, "fine") for t in times]
    assert len(many) == 3 and all(s.num_gaussians == model.num_gaussians for s in many)
    for got, expected in zip(many, one_by_one):
        _assert_states_close(got, expected)
    assert not torch.allclose(many[0].means, many[1].means)  # the times really differ

    def grads(states) -> list[torch.Tensor]:
        loss = sum((k + 1) * (s.means.square().sum() + s.log_scales.sum()) for k, s in enumerate(states))
        params = [model._xyz, *model.deformation.get_mlp_parameters()]
        return torch.autograd.grad(loss, params, allow_unused=True)

    for got, expected in zip(grads(model.deform_many(times, "fine")), grads([model.deform(t, "fine") for t in times])):
        if expected is None:
            assert got is None
        else:
            torch.testing.assert_close(got, expected, atol=1e-4, rtol=1e-4)
    # coarse, one time, or a time outside the span: deform's own path (clamping, extrapolation)
    assert model.deform_many([0.5, 0.6], "coarse")[0].means is model._xyz
    model.set_time_span((0.1, 0.8), "linear")
    for got, t in zip(model.deform_many([0.0, 0.5], "fine"), (0.0, 0.5)):
        _assert_states_close(got, model.deform(t, "fine"))


def test_deform_many_shared_rows_take_the_other_times_state_and_send_their_gradients_there(monkeypatch):
    """`shared[k] = (j, mask)`: the masked rows at times[k] are the state at times[j] (values and
    gradients, against one deform per time and torch.where as the oracle), the others times[k]'s
    own; the module is not asked to deform the masked rows at times[k]; deform's path agrees."""
    times = (0.2, 0.9, 0.6)
    model = model_with_time_dependent_planes()
    model.training_setup(opt_args())
    n = model.num_gaussians
    mask = torch.arange(n) % 3 != 0
    shared = [None, (0, mask), None]
    one_by_one = [model.deform(t, "fine") for t in times]

    def oracle(states):
        return [states[0], states[1].replace(**{name: torch.where(mask.unsqueeze(1), getattr(states[0], name),
                                                                  getattr(states[1], name))
                                                for name in ("means", "log_scales", "rotations")}), states[2]]

    many = model.deform_many(times, "fine", shared=shared)
    for got, expected in zip(many, oracle(one_by_one)):
        _assert_states_close(got, expected)
    assert not torch.allclose(many[1].means[~mask], many[0].means[~mask])  # unshared rows keep their own time

    def grads(states) -> list[torch.Tensor]:
        loss = sum((k + 1) * (s.means.square().sum() + s.log_scales.sum()) for k, s in enumerate(states))
        return torch.autograd.grad(loss, [model._xyz, *model.deformation.get_mlp_parameters()], allow_unused=True)

    for got, expected in zip(grads(model.deform_many(times, "fine", shared=shared)),
                             grads(oracle([model.deform(t, "fine") for t in times]))):
        if expected is None:
            assert got is None
        else:
            torch.testing.assert_close(got, expected, atol=1e-4, rtol=1e-4)
    seen = {}
    forward = model.deformation.forward
    monkeypatch.setattr(model.deformation, "forward", lambda state, t, buffers=None: (
        seen.update(used=buffers.get("row_used")), forward(state, t, buffers))[1])
    model.deform_many(times, "fine", rows=[None, None, mask], shared=shared)
    expected_used = torch.cat([torch.ones(n, dtype=torch.bool), ~mask, mask])
    assert torch.equal(seen["used"], expected_used)
    # deform's path (a time outside the span) shares the same way
    model.set_time_span((0.3, 0.95), "linear")
    for got, expected in zip(model.deform_many(times, "fine", shared=shared),
                             oracle([model.deform(t, "fine") for t in times])):
        _assert_states_close(got, expected)
    for bad, match in (([None, (1, mask), None], "another"), ([None, (0, mask)], "entries"),
                       ([None, (0, mask[:-1]), None], "bool"), ([(2, mask), (0, mask), None], "share none")):
        with pytest.raises(ValueError, match=match):
            model.deform_many(times, "fine", shared=bad)


def test_fields_the_deformation_passes_through_stay_the_canonical_tensor_with_equal_gradients():
    """4DGS's disabled heads (SH, opacity) leave those fields as they are: deform_many hands every
    time the canonical tensor itself (no [kN] slices), with the per-time call's values and gradients."""
    times = (0.2, 0.9)
    model = model_with_time_dependent_planes()
    model.training_setup(opt_args())
    many = model.deform_many(times, "fine")
    assert many[0].shs is many[1].shs and many[0].opacity_logits is many[1].opacity_logits
    assert many[0].means is not many[1].means

    def grads(states) -> list[torch.Tensor]:
        loss = sum((k + 1) * (s.shs.square().sum() + s.opacity_logits.sum() + s.means.sum())
                   for k, s in enumerate(states))
        return torch.autograd.grad(loss, [model._features_dc, model._features_rest, model._opacity, model._xyz])

    for got, expected in zip(grads(model.deform_many(times, "fine")), grads([model.deform(t, "fine") for t in times])):
        torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)


def test_deform_passes_registered_buffers_to_the_module():
    seen = {}

    class Recorder(torch.nn.Module):
        def forward(self, state, times, buffers=None):
            seen.update(buffers)
            seen["times"] = times
            return state

        def set_aabb(self, xyz_max, xyz_min):
            pass

    model = GaussianModel(1, None, deformation=Recorder())
    model.create_from_pcd(np.random.default_rng(0).uniform(size=(5, 3)), np.zeros((5, 3)), 1.0)
    flags = torch.tensor([True, False, True, False, True])
    model.register_gaussian_buffer("is_dynamic", flags)
    model.deform(0.25, "fine")
    assert torch.equal(seen["is_dynamic"], flags)
    assert seen["times"].shape == (5, 1) and torch.all(seen["times"] == 0.25)


def test_add_densification_stats_converts_pixels_to_ndc():
    model = make_model(count=4)
    grads = torch.tensor([[2.0, 0.0], [0.0, 3.0], [3.0, 4.0], [5.0, 5.0]])
    visible = torch.tensor([True, True, True, False])
    model.add_densification_stats(grads, visible, width=100, height=50)
    model.add_densification_stats(grads, visible, width=100, height=50)
    # x * W/2 = x * 50, y * H/2 = y * 25
    expected = torch.tensor([[200.0], [150.0], [2 * math.hypot(150.0, 100.0)], [0.0]])
    torch.testing.assert_close(model.xyz_gradient_accum, expected)
    torch.testing.assert_close(model.denom, torch.tensor([[2.0], [2.0], [2.0], [0.0]]))
    with pytest.raises(ValueError, match="means2d_grad"):
        model.add_densification_stats(grads[:3], visible, 100, 50)


def _train_step(model, seed):
    generator = torch.Generator().manual_seed(seed)
    state = model.deform(0.3, "fine")
    weights = [torch.randn(t.shape, generator=generator) for t in (state.means, state.log_scales, state.shs)]
    loss = sum((w * t).sum() for w, t in zip(weights, (state.means, state.log_scales, state.shs)))
    loss = loss + state.opacities.sum() + model.compute_regulation(0.01, 1e-4, 1e-4)
    for param in model.registered_parameters.values():
        loss = loss + (param * torch.randn(param.shape, generator=generator)).sum()
    loss.backward()
    model.optimizer.step()
    model.optimizer.zero_grad(set_to_none=True)


def test_freeze_blocks_updates_including_momentum():
    model = make_model()
    _train_step(model, 0)  # builds Adam momentum for every group
    deformation_before = [p.detach().clone() for p in model.deformation.parameters()]
    model.freeze(["deformation", "grid"])
    xyz_before = model._xyz.detach().clone()
    for seed in (1, 2):
        _train_step(model, seed)
    for before, after in zip(deformation_before, model.deformation.parameters()):
        assert torch.equal(before, after)
    assert not torch.equal(xyz_before, model._xyz)
    model.unfreeze(["deformation", "grid"])
    assert model.deformation.deformation_net.grid.aabb.requires_grad is False
    _train_step(model, 3)
    changed = [not torch.equal(b, a) for b, a in zip(deformation_before, model.deformation.parameters())]
    assert sum(changed) > len(changed) // 2
    with pytest.raises(ValueError, match="unknown parameter group"):
        model.freeze(["mlp"])


def test_frozen_per_gaussian_group_stays_frozen_through_densification():
    model = make_model()
    model.freeze("opacity")
    model.densify_and_clone(torch.ones(40, 1), 0.5, scene_extent=1e6)
    assert model._opacity.requires_grad is False and model._xyz.requires_grad is True
    model.unfreeze("opacity")
    assert model._opacity.requires_grad is True


def test_registered_parameter_is_optimized_in_its_own_group():
    model = make_model()
    param = model.register_gaussian_parameter("motion_weight", torch.zeros(40, 2), lr=0.1)
    assert model.optimizer.param_groups[-1]["name"] == "motion_weight"
    assert model.optimizer.param_groups[-1]["lr"] == 0.1
    _train_step(model, 0)
    assert model.registered_parameters["motion_weight"].abs().min() > 0.05  # Adam's first step ~ lr
    assert param is model.registered_parameters["motion_weight"]
    with pytest.raises(ValueError, match="first dimension"):
        model.register_gaussian_buffer("bad", torch.zeros(39))
    with pytest.raises(ValueError, match="already exists"):
        model.register_gaussian_buffer("xyz", torch.zeros(40))


def _clone_model(source):
    model = GaussianModel(source.max_sh_degree, hidden_args())
    return model


def test_capture_restore_gives_identical_next_step():
    model = make_model()
    model.register_gaussian_buffer("is_dynamic", torch.arange(40) % 3 == 0)
    model.register_gaussian_parameter("extra", torch.randn(40, 2), lr=0.01)
    _train_step(model, 0)
    model.add_densification_stats(torch.rand(40, 2), torch.ones(40, dtype=torch.bool), 64, 48)
    model.freeze("grid")
    model.active_sh_degree = 2
    captured = model.capture()

    restored = _clone_model(model)
    restored.restore(captured, opt_args())
    torch.manual_seed(5)
    _train_step(model, 11)
    torch.manual_seed(5)
    _train_step(restored, 11)
    for name in ("_xyz", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity"):
        assert torch.equal(getattr(model, name), getattr(restored, name)), name
    for a, b in zip(model.deformation.parameters(), restored.deformation.parameters()):
        assert torch.equal(a, b)
    assert torch.equal(model.registered_parameters["extra"], restored.registered_parameters["extra"])
    assert torch.equal(restored.registered_buffers["is_dynamic"], torch.arange(40) % 3 == 0)
    assert torch.equal(model.xyz_gradient_accum, restored.xyz_gradient_accum)
    assert restored.frozen_groups == ["grid"] and restored.active_sh_degree == 2


def test_restore_accepts_4dgs_capture_tuple():
    model = make_model()
    _train_step(model, 0)
    four_dgs_capture = model.capture()[:14]  # what 4DGS's train.py saves
    target = _clone_model(model)
    target.restore(four_dgs_capture, opt_args())
    target.register_gaussian_parameter("extra", torch.zeros(40, 1), lr=0.01)
    saved = model.optimizer.state_dict()
    restored_state = target.optimizer.state_dict()
    assert len(restored_state["param_groups"]) == 9
    for index in saved["state"]:
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(saved["state"][index][key], restored_state["state"][index][key])
    with pytest.raises(ValueError, match="_features_rest"):
        GaussianModel(1, hidden_args()).restore(four_dgs_capture, opt_args())


def test_restore_rejects_foreign_optimizer_state_before_changing_the_model():
    """Checked before anything is installed: the target keeps its Gaussians."""
    model = make_model()
    _train_step(model, 0)
    captured = list(model.capture())
    renamed = copy.deepcopy(captured[12])
    renamed["param_groups"][0]["name"] = "positions"
    target = make_model(count=7, seed=2)
    with pytest.raises(ValueError, match=r"chk\.pth: optimizer groups \['positions'\]"):
        target.restore(tuple(captured[:12] + [renamed] + captured[13:]), opt_args(), source="chk.pth")
    wrong_shape = copy.deepcopy(captured[12])
    wrong_shape["state"][0]["exp_avg"] = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="exp_avg.*group 'xyz'"):
        target.restore(tuple(captured[:12] + [wrong_shape] + captured[13:]), opt_args(), source="chk.pth")
    assert target.num_gaussians == 7 and target.optimizer is not None


def test_deform_many_repeats_only_the_fields_the_module_reads(monkeypatch):
    """The fields the module passes through unread (passed_through(): 4DGS's disabled heads) reach
    it as zero-stride stand-ins, not as k copies of the [N, K, 3] SH; a module that changes such a
    field anyway is named instead of rendering the stand-in."""
    model = model_with_time_dependent_planes()
    module = type(model.deformation)
    assert model.deformation.passed_through() == {"opacity_logits", "shs"}
    seen = {}
    real = module.forward

    def spy(self, state, times, buffers=None):
        seen["state"] = state
        return real(self, state, times, buffers)

    monkeypatch.setattr(module, "forward", spy)
    model.deform_many((0.2, 0.9, 0.4), "fine")
    given, n = seen["state"], model.num_gaussians
    assert given.shs.shape == (3 * n, *model.canonical_state().shs.shape[1:])
    assert given.shs.stride() == (0, 0, 0) and given.opacity_logits.stride() == (0, 0)
    assert given.means.stride(0) == 3 and given.means.shape == (3 * n, 3)

    monkeypatch.setattr(module, "forward", lambda self, state, times, buffers=None:
                        real(self, state, times, buffers).replace(shs=state.shs + 0.0))
    with pytest.raises(RuntimeError, match="changed shs"):
        model.deform_many((0.2, 0.9), "fine")


def test_passed_through_fields_follow_the_disabled_heads():
    from baselines.fourdgs.deformation import DeformNetwork

    assert DeformNetwork(hidden_args()).passed_through() == {"opacity_logits", "shs"}
    assert DeformNetwork(hidden_args(no_dshs=False, no_ds=True)).passed_through() == {"opacity_logits", "log_scales"}
    assert DeformNetwork(hidden_args(no_do=False, no_dshs=False)).passed_through() == frozenset()
