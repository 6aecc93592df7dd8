"""`static_decoder field`: static Gaussians through a second, whole-scene 4DGS field at 4DGS's own rates."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.fourdgs.checkpoint import load_point_cloud_dir, save_point_cloud_dir
from baselines.fourdgs.deformation import DeformNetwork
from baselines.fourdgs.gaussian_model import GaussianModel
from reflow_plugin.params import ReFlowParams
from reflow_plugin.plugin import ReFlowPlugin
from reflow_plugin.separation import SeparatedDeformation
from tests._model_helpers import hidden_args, opt_args


def _model(count: int = 60, seed: int = 0, decoder: str = "field") -> GaussianModel:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = GaussianModel(3, hidden_args(), deformation=SeparatedDeformation(hidden_args(), static_decoder=decoder))
    model.create_from_pcd(rng.uniform(-1, 1, (count, 3)), rng.uniform(0, 1, (count, 3)), spatial_lr_scale=2.0)
    model.set_deformation_table(torch.arange(count) % 3 == 0)
    model.training_setup(opt_args())
    return model


def _perturb(network) -> None:
    """Give a zero-initialised 4DGS network time dependence and non-zero outputs."""
    with torch.no_grad():
        for level in network.deformation_net.grid.grids:
            for index in (2, 4, 5):
                level[index].add_(0.3 * torch.randn_like(level[index]))
        for name in ("pos_deform", "scales_deform", "rotations_deform"):
            getattr(network.deformation_net, name)[3].weight.normal_(0.0, 0.5)


def test_the_field_starts_as_the_identity_and_then_moves_static_rows_as_4dgs_s_network():
    model = _model()
    canonical = model.canonical_state()
    torch.testing.assert_close(model.deform(0.8, "fine").means, canonical.means)  # zero-initialised heads
    _perturb(model.deformation.static_field)
    table = model.deformation_table
    early, late = model.deform(0.1, "fine"), model.deform(0.9, "fine")
    assert not torch.allclose(early.means[~table], late.means[~table])  # static rows now vary in time
    times = torch.full((int((~table).sum()), 1), 0.9)
    expected = model.deformation.static_field(canonical.index(~table), times)
    for field in ("means", "log_scales", "rotations"):
        torch.testing.assert_close(getattr(late, field)[~table], getattr(expected, field), msg=field)


def test_the_dynamic_rows_are_the_same_with_or_without_the_field():
    field, plain = _model(decoder="field"), _model(decoder="none")
    _perturb(field.deformation)  # the dynamic branch (the module's own 4DGS network)
    plain.deformation.load_state_dict({k: v for k, v in field.deformation.state_dict().items()
                                       if not k.startswith("static_field.")})
    _perturb(field.deformation.static_field)
    table = field.deformation_table
    torch.testing.assert_close(field.deform(0.6, "fine").means[table], plain.deform(0.6, "fine").means[table])


def test_the_field_has_its_own_groups_on_4dgs_rates_untouched_by_the_dynamic_multiplier():
    model = _model()
    rates = {g["name"]: g["lr"] for g in model.optimizer.param_groups}
    assert rates["static_deformation"] == rates["deformation"] and rates["static_grid"] == rates["grid"]
    model.scale_learning_rate("deformation", 10.0)
    model.scale_learning_rate("grid", 10.0)
    later = model.update_learning_rate(500)
    opt = opt_args()
    assert later["deformation"] == 10.0 * later["static_deformation"]
    assert later["grid"] == 10.0 * later["static_grid"]
    assert later["static_deformation"] < opt.deformation_lr_init * 2.0  # the schedule decays it too
    field_ids = {id(p) for p in model.deformation.static_field.parameters()}
    owned = {g["name"]: {id(p) for p in g["params"]} for g in model.optimizer.param_groups}
    assert owned["static_deformation"] | owned["static_grid"] == field_ids
    assert not field_ids & (owned["deformation"] | owned["grid"])


def test_a_step_trains_the_field_and_a_checkpoint_keeps_it(tmp_path):
    model = _model()
    _perturb(model.deformation.static_field)  # gradients reach the planes only once the heads are non-zero
    planes = [p.detach().clone() for p in model.deformation.static_field.get_grid_parameters()]
    loss = model.deform(0.7, "fine").means[~model.deformation_table].square().sum()
    loss.backward()
    model.optimizer.step()
    after = model.deformation.static_field.get_grid_parameters()
    assert any(not torch.equal(a, b) for a, b in zip(after, planes))
    save_point_cloud_dir(model, tmp_path / "pc")
    other = GaussianModel(3, hidden_args(), deformation=SeparatedDeformation(hidden_args(), static_decoder="field"))
    load_point_cloud_dir(tmp_path / "pc", other)
    torch.testing.assert_close(other.deform(0.7, "fine").means, model.deform(0.7, "fine").means)


def test_fit_box_narrows_the_dynamic_branch_only_and_the_regulariser_counts_both():
    model = _model()
    whole = [t.clone() for t in model.deformation.static_field.get_aabb]
    model.deformation.fit_box(torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.2, 0.2]]), 0.1)
    for kept, now in zip(whole, model.deformation.static_field.get_aabb):
        torch.testing.assert_close(now, kept)
    assert float(model.deformation.get_aabb[0][0]) < float(whole[0][0])
    weights = (1.0, 0.5, 0.25)
    _perturb(model.deformation.static_field)  # its time planes now cost something
    total = model.deformation.compute_regulation(*weights)
    dynamic = DeformNetwork.compute_regulation(model.deformation, *weights)
    static = model.deformation.static_field.compute_regulation(*weights)
    assert float(static.detach()) > 0
    torch.testing.assert_close(total, dynamic + static)


def test_an_exact_resume_restores_the_field_and_its_optimizer_state():
    model = _model()
    _perturb(model.deformation.static_field)
    model.deform(0.4, "fine").means[~model.deformation_table].square().sum().backward()
    model.optimizer.step()
    resumed = _model(seed=1)
    resumed.restore(model.capture(), opt_args())
    torch.testing.assert_close(resumed.deform(0.4, "fine").means, model.deform(0.4, "fine").means)
    saved = {g["name"]: g["params"] for g in model.optimizer.param_groups}
    compared = 0
    for group in resumed.optimizer.param_groups:
        if group["name"].startswith("static_"):
            for mine, theirs in zip(group["params"], saved[group["name"]]):
                if "exp_avg" in model.optimizer.state.get(theirs, {}):  # parameters that had a gradient
                    torch.testing.assert_close(resumed.optimizer.state[mine]["exp_avg"],
                                               model.optimizer.state[theirs]["exp_avg"])
                    compared += 1
    assert compared > 0


def test_a_static_decoder_without_separation_is_refused():
    everything = frozenset(ReFlowPlugin.components)
    for decoder in ("field", "triplane"):
        params = {"ReFlowParams": ReFlowParams(static_decoder=decoder)}
        assert ReFlowPlugin(params, everything).static_decoder == decoder
        with pytest.raises(ValueError, match=f"--static_decoder {decoder} needs the separation component"):
            ReFlowPlugin(params, everything - {"separation"})
    # the default (auto): the field with separation, none without it (the ablation row still runs)
    assert ReFlowParams().static_decoder == "auto"
    assert ReFlowPlugin({"ReFlowParams": ReFlowParams()}, everything).static_decoder == "field"
    assert ReFlowPlugin({"ReFlowParams": ReFlowParams()}, everything - {"separation"}).static_decoder == "none"
    assert ReFlowPlugin({"ReFlowParams": ReFlowParams(static_decoder="none")}, everything).static_decoder == "none"


def test_partners_read_the_static_field_at_their_views_time_and_the_views_are_unchanged(monkeypatch):
    """ReFlowPlugin.partner_shared_rows (the field only): per projected partner, its batch view and
    the static rows; through deform_many the partner's static rows equal the view's (the field's
    value at the view's time), its dynamic rows stay at the partner's own time, the views are the
    same as without sharing; `none`, the switch, or no projected partner: nothing shared."""
    from types import SimpleNamespace

    from reflow_plugin.plugin import PARTNER_STATIC_SWITCH

    model = _model()
    _perturb(model.deformation)
    _perturb(model.deformation.static_field)
    table = model.deformation_table
    everything = frozenset(ReFlowPlugin.components)
    plugin = ReFlowPlugin({"ReFlowParams": ReFlowParams()}, everything)
    views = [SimpleNamespace(time=0.1), SimpleNamespace(time=0.4), SimpleNamespace(time=0.7)]
    plugin._partner_cameras = [SimpleNamespace(time=0.3), None, SimpleNamespace(time=0.9)]
    plugin._partners_projected = True
    ctx = SimpleNamespace(model=model, batch=views)
    shared = plugin.partner_shared_rows(ctx)
    assert [k for k, _ in shared] == [0, 2] and all(torch.equal(mask, ~table) for _, mask in shared)
    times = (0.1, 0.4, 0.7, 0.3, 0.9)
    alone = model.deform_many(times, "fine")
    together = model.deform_many(times, "fine", shared=[None, None, None, *shared])
    for k in range(3):
        torch.testing.assert_close(together[k].means, alone[k].means)
    for partner, view in ((3, 0), (4, 2)):
        torch.testing.assert_close(together[partner].means[~table], alone[view].means[~table])
        torch.testing.assert_close(together[partner].means[table], alone[partner].means[table])
        assert not torch.allclose(alone[partner].means[~table], alone[view].means[~table])  # the field moves them
    monkeypatch.setenv(PARTNER_STATIC_SWITCH, "0")
    assert plugin.partner_shared_rows(ctx) is None
    monkeypatch.delenv(PARTNER_STATIC_SWITCH)
    rigid = ReFlowPlugin({"ReFlowParams": ReFlowParams(static_decoder="none")}, everything)
    rigid._partner_cameras, rigid._partners_projected = plugin._partner_cameras, True
    assert rigid.partner_shared_rows(ctx) is None
    plugin._partners_projected = False
    assert plugin.partner_shared_rows(ctx) is None
