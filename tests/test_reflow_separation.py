"""Separated deformation and its labels: static rows never move, labels follow every row edit."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.fourdgs.checkpoint import load_point_cloud_dir, save_point_cloud_dir
from baselines.fourdgs.deformation import DeformNetwork
from baselines.fourdgs.gaussian_model import GaussianModel
from reflow_plugin.separation import TIME_CENTER, SeparatedDeformation
from tests._model_helpers import hidden_args, opt_args


def _model(count=60, dynamic_every=3, seed=0, **options) -> GaussianModel:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = GaussianModel(3, hidden_args(), deformation=SeparatedDeformation(hidden_args(), **options))
    model.create_from_pcd(rng.uniform(-1, 1, (count, 3)), rng.uniform(0, 1, (count, 3)), spatial_lr_scale=2.0)
    model.set_deformation_table(torch.arange(count) % dynamic_every == 0)
    model.training_setup(opt_args())
    return model


def test_state_dict_has_4dgs_keys_and_loads_4dgs_weights():
    torch.manual_seed(0)
    plain = DeformNetwork(hidden_args())
    torch.manual_seed(0)
    separated = SeparatedDeformation(hidden_args(), zero_init=False)
    assert separated.state_dict().keys() == plain.state_dict().keys()
    for key, value in plain.state_dict().items():  # same seed, same initial weights as 4DGS
        torch.testing.assert_close(separated.state_dict()[key], value)
    separated.load_state_dict(plain.state_dict(), strict=True)
    with_decoder = SeparatedDeformation(hidden_args(), static_decoder="triplane")
    assert any(k.startswith("static_decoder.") for k in with_decoder.state_dict())


@pytest.mark.parametrize("decoder", ["none", "triplane"])
def test_static_gaussians_do_not_move_over_time(decoder):
    model = _model(static_decoder=decoder, zero_init=False)
    with torch.no_grad():  # time planes start at 1 (no time dependence): give them some
        for level in model.deformation.deformation_net.grid.grids:
            for index in (2, 4, 5):
                level[index].add_(0.3 * torch.randn_like(level[index]))
        if decoder == "triplane":
            model.deformation.static_decoder.net[2].weight.normal_(0.0, 0.5)
    table = model.deformation_table
    early, late = model.deform(0.0, "fine"), model.deform(1.0, "fine")
    for field in ("means", "log_scales", "rotations", "opacity_logits", "shs"):
        torch.testing.assert_close(getattr(early, field)[~table], getattr(late, field)[~table], msg=field)
    assert not torch.allclose(early.means[table], late.means[table])  # the dynamic rows do move


def test_all_dynamic_equals_4dgs_and_all_static_skips_the_network():
    torch.manual_seed(3)
    plain = DeformNetwork(hidden_args())
    model = _model(zero_init=False)
    model.deformation.load_state_dict(plain.state_dict())
    state = model.canonical_state()
    times = torch.full((model.num_gaussians, 1), 0.7)
    everything = torch.ones(model.num_gaussians, dtype=torch.bool)
    out = model.deformation(state, times, {"deformation_table": everything})
    torch.testing.assert_close(out.means, plain(state, times).means)

    calls = []
    handle = model.deformation.deformation_net.register_forward_hook(lambda *a: calls.append(1))
    nothing = torch.zeros(model.num_gaussians, dtype=torch.bool)
    out = model.deformation(state, times, {"deformation_table": nothing})
    handle.remove()
    assert not calls and out.means is state.means  # the dynamic branch never ran


def test_zero_init_starts_at_the_canonical_place():
    model = _model(zero_init=True)
    moved = model.deform(0.9, "fine")
    torch.testing.assert_close(moved.means, model.canonical_state().means)


def test_cost_follows_the_dynamic_rows():
    model = _model(count=200, dynamic_every=10)
    seen = []
    handle = model.deformation.deformation_net.grid.register_forward_hook(lambda m, args, out: seen.append(args[0].shape[0]))
    model.deform(0.5, "fine")
    handle.remove()
    assert seen == [20]  # only the 20 dynamic rows reach the HexPlane


def test_labels_survive_clone_split_prune_save_and_load(tmp_path):
    model = _model(count=60)
    table = model.deformation_table.clone()
    xyz = model.get_xyz.detach().clone()
    grads = torch.full((60, 1), 1.0)
    model.percent_dense = 10.0  # every Gaussian counts as small: clone all
    model.densify_and_clone(grads, 0.5, 1.0)
    assert model.num_gaussians == 120
    torch.testing.assert_close(model.get_xyz.detach()[60:], xyz)
    assert torch.equal(model.deformation_table[60:], table)
    model.percent_dense = 0.0  # every Gaussian counts as large: split all
    model.densify_and_split(torch.full((120, 1), 1.0), 0.5, 1.0)
    assert model.num_gaussians == 240
    assert int(model.deformation_table.sum()) == 4 * int(table.sum())
    drop = torch.zeros(240, dtype=torch.bool)
    drop[::7] = True
    kept = model.deformation_table[~drop].clone()
    model.prune_points(drop)
    assert torch.equal(model.deformation_table, kept)
    save_point_cloud_dir(model, tmp_path / "pc")
    other = GaussianModel(3, hidden_args(), deformation=SeparatedDeformation(hidden_args()))
    load_point_cloud_dir(tmp_path / "pc", other)
    assert torch.equal(other.deformation_table, kept)


def test_fit_box_covers_the_dynamic_points():
    model = _model(count=30)
    points = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 0.0]])  # flat in z
    model.deformation.fit_box(points, 0.25)
    xyz_max, xyz_min = model.deformation.get_aabb
    assert torch.all(xyz_max > points.max(0).values) and torch.all(xyz_min < points.min(0).values)
    assert float(xyz_max[2] - xyz_min[2]) > 0.5  # a flat axis gets a real extent


def test_temporal_window_keeps_values_and_gradients_finite():
    from reflow_plugin.separation import temporal_window

    logits = torch.zeros(4, 1, requires_grad=True)
    times = torch.tensor([[0.5], [0.5], [0.0], [1.0]])
    centers = torch.tensor([[0.5], [0.4], [1.0], [1.0]])
    log_scales = torch.log(torch.tensor([[0.1], [0.1], [1e-4], [1e3]])).requires_grad_()
    out = temporal_window(logits, times, centers, log_scales)
    opacity = torch.sigmoid(out).squeeze(1).detach()
    assert opacity[0] == pytest.approx(0.5, abs=1e-6)  # at the centre: unchanged
    assert opacity[1] == pytest.approx(0.5 * np.exp(-0.5), rel=1e-5)  # one sigma away
    assert opacity[2] < 1e-5 and opacity[3] == pytest.approx(0.5, abs=1e-6)  # far outside / infinite window
    out.sum().backward()
    assert torch.isfinite(logits.grad).all() and torch.isfinite(log_scales.grad).all()


def test_windows_apply_to_dynamic_rows_only():
    from reflow_plugin.separation import TIME_CENTER, TIME_LOG_SCALE

    model = _model(count=30)
    model.register_gaussian_buffer(TIME_CENTER, torch.full((30, 1), 0.2))
    model.register_gaussian_parameter(TIME_LOG_SCALE, torch.full((30, 1), float(np.log(0.05))), 0.01)
    table = model.deformation_table
    early, late = model.deform(0.2, "fine"), model.deform(0.9, "fine")
    torch.testing.assert_close(early.opacity_logits[~table], late.opacity_logits[~table])
    assert (torch.sigmoid(late.opacity_logits[table]) < 1e-4).all()
    torch.testing.assert_close(early.opacity_logits[table], model._opacity.detach()[table], atol=1e-5, rtol=0)


def test_keyframes_spread_over_time():
    import types

    from reflow_plugin.seeding import keyframes, window_scale

    cams = [types.SimpleNamespace(time=t) for t in np.linspace(0, 1, 20)]
    masks = [np.ones((2, 2), bool) for _ in cams]
    masks[0][:] = False  # an empty mask never becomes a keyframe
    frames = keyframes(cams, masks, 5, reference=13)
    assert len(frames) == 5 and 13 in frames and 0 not in frames
    assert frames == sorted(frames) and frames[0] == 1 and frames[-1] == 19
    assert keyframes(cams, masks, 1, reference=7) == [7]
    assert window_scale([0.0, 0.5, 1.0]) == pytest.approx(0.3)
    assert window_scale([0.3]) == float("inf")


def test_window_cull_deforms_only_the_copies_alive_at_t():
    from reflow_plugin.separation import TIME_CENTER, TIME_LOG_SCALE

    states = {}
    for cull in (0.0, 1e-3):
        model = _model(count=60, zero_init=False, window_cull=cull)
        torch.manual_seed(1)
        with torch.no_grad():  # time planes start at 1 (no time dependence): give them some
            for level in model.deformation.deformation_net.grid.grids:
                for index in (2, 4, 5):
                    level[index].add_(0.3 * torch.randn_like(level[index]))
        centers = torch.where(torch.arange(60) % 2 == 0, 0.2, 0.8).unsqueeze(1)  # two keyframe copies
        model.register_gaussian_buffer(TIME_CENTER, centers)
        model.register_gaussian_parameter(TIME_LOG_SCALE, torch.full((60, 1), float(np.log(0.05))), 0.01)
        states[cull] = model.deform(0.25, "fine"), model.canonical_state()
    (full, canonical), (culled, _) = states[0.0], states[1e-3]
    table = model.deformation_table
    alive = table & (torch.arange(60) % 2 == 0)  # window weight at t=0.25: 0.61 (copy at 0.2), ~1e-32 (0.8)
    dead = table & ~alive
    for field in ("means", "log_scales", "rotations", "shs"):
        torch.testing.assert_close(getattr(culled, field)[alive], getattr(full, field)[alive], msg=field)
        torch.testing.assert_close(getattr(culled, field)[dead], getattr(canonical, field)[dead], msg=field)
    assert not torch.allclose(full.means[dead], canonical.means[dead])  # without the cull they were deformed
    assert (torch.sigmoid(culled.opacity_logits[dead]) < 1e-6).all()  # and invisible either way
    torch.testing.assert_close(culled.opacity_logits[alive], full.opacity_logits[alive])


@pytest.mark.parametrize("anchored", [False, True])
def test_the_network_gets_stand_ins_for_the_fields_it_passes_through(anchored, monkeypatch):
    """The dynamic rows reach the network without their SH and opacity gathered (zero-stride
    stand-ins); the result equals the network on fully gathered rows, and the SH and opacity of
    every row stay the input's own tensors."""
    model = _model(zero_init=False, relative_time=anchored, anchored=anchored)
    with torch.no_grad():
        for level in model.deformation.deformation_net.grid.grids:
            for index in (2, 4, 5):
                level[index].add_(0.3 * torch.randn_like(level[index]))
    module = model.deformation
    assert module.passed_through() == {"shs"}  # the opacity is the temporal windows' to change
    assert SeparatedDeformation(hidden_args(), static_decoder="triplane").passed_through() == {"shs"}
    inner = type(module.deformation_net)
    seen = []
    real = inner.forward
    monkeypatch.setattr(inner, "forward", lambda self, state, times: seen.append(state) or real(self, state, times))
    state, table = model.canonical_state(), model.deformation_table
    times = torch.full((model.num_gaussians, 1), 0.7)
    buffers = {"deformation_table": table}
    if anchored:  # keyframe centres at 0: relative time tau = t, the anchored path D(x, tau) - D(x, 0)
        buffers[TIME_CENTER] = torch.zeros(model.num_gaussians, 1)
    out = module(state, times, buffers)
    assert len(seen) == 1
    assert seen[0].shs.stride() == (0, 0, 0) and seen[0].opacity_logits.stride() == (0, 0)
    assert out.shs is state.shs and out.opacity_logits is state.opacity_logits
    monkeypatch.setattr(inner, "forward", real)
    rows = table.nonzero().squeeze(1)
    gathered = state.index(rows)
    if anchored:
        moved = DeformNetwork.forward(module, gathered, times[rows])
        zero = DeformNetwork.forward(module, gathered, torch.zeros_like(times[rows]))
        expected = gathered.means + (moved.means - zero.means)
    else:
        expected = DeformNetwork.forward(module, gathered, times[rows]).means
    torch.testing.assert_close(out.means[rows], expected, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(out.means[~table], state.means[~table], rtol=0, atol=0)
