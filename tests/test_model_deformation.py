"""Deformation network: 4DGS state-dict layout, outputs equal to 4DGS's layer-by-layer recipe."""

import itertools

import pytest
import torch

from baselines.fourdgs.deformation import DeformNetwork, check_deformation_state, load_deformation_state
from baselines.fourdgs.state import GaussianState
from benchmarks.deformation import PlainDeformNetwork
from tests._model_helpers import hidden_args


def expected_4dgs_state_shapes(args) -> dict[str, tuple[int, ...]]:
    """Key -> shape of 4DGS's deform_network.state_dict(), derived from its source.

    deform_network registers timenet (Linear(2*timebase_pe+1, timenet_width), ReLU,
    Linear(timenet_width, timenet_output)), deformation_net and 4 frequency buffers;
    Deformation holds grid (HexPlaneField: aabb [2,3], grids.<level>.<plane>), feature_out
    (Linear(feat_dim, W) then (ReLU, Linear(W, W)) x (D-1)) and five heads
    Sequential(ReLU, Linear(W,W), ReLU, Linear(W,out)) with out 3, 3, 4, 1, 48.
    """
    width, depth = args.net_width, args.defor_depth
    config = args.kplanes_config
    channels, resolution = config["output_coordinate_dim"], config["resolution"]
    table = {
        "time_poc": (args.timebase_pe,),
        "pos_poc": (args.posebase_pe,),
        "rotation_scaling_poc": (args.scale_rotation_pe,),
        "opacity_poc": (args.opacity_pe,),
        "timenet.0.weight": (args.timenet_width, 2 * args.timebase_pe + 1),
        "timenet.0.bias": (args.timenet_width,),
        "timenet.2.weight": (args.timenet_output, args.timenet_width),
        "timenet.2.bias": (args.timenet_output,),
        "deformation_net.grid.aabb": (2, 3),
    }
    for level, multiplier in enumerate(args.multires):
        scaled = [r * multiplier for r in resolution[:3]] + [resolution[3]]
        for plane, (a, b) in enumerate(itertools.combinations(range(4), 2)):
            table[f"deformation_net.grid.grids.{level}.{plane}"] = (1, channels, scaled[b], scaled[a])
    feat_dim = channels * len(args.multires)
    table["deformation_net.feature_out.0.weight"] = (width, feat_dim)
    table["deformation_net.feature_out.0.bias"] = (width,)
    for i in range(depth - 1):
        table[f"deformation_net.feature_out.{2 * i + 2}.weight"] = (width, width)
        table[f"deformation_net.feature_out.{2 * i + 2}.bias"] = (width,)
    for head, out in [("pos_deform", 3), ("scales_deform", 3), ("rotations_deform", 4), ("opacity_deform", 1),
                      ("shs_deform", 48)]:
        table[f"deformation_net.{head}.1.weight"] = (width, width)
        table[f"deformation_net.{head}.1.bias"] = (width,)
        table[f"deformation_net.{head}.3.weight"] = (out, width)
        table[f"deformation_net.{head}.3.bias"] = (out,)
    return table


LEGO = dict(kplanes_config={"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 32,
                            "resolution": [64, 64, 64, 25]}, multires=[1, 2], defor_depth=0, net_width=64)
HYPERNERF = dict(kplanes_config={"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 16,
                                 "resolution": [64, 64, 64, 150]}, multires=[1, 2, 4], defor_depth=1, net_width=128)


@pytest.mark.parametrize("config", [LEGO, HYPERNERF, dict(defor_depth=3)], ids=["lego", "hypernerf", "deep"])
def test_state_dict_keys_and_shapes_equal_4dgs(config):
    args = hidden_args(**config)
    state = DeformNetwork(args).state_dict()
    assert {k: tuple(v.shape) for k, v in state.items()} == expected_4dgs_state_shapes(args)
    assert state["pos_poc"].tolist() == [2.0**i for i in range(args.posebase_pe)]


def _state(count: int, generator: torch.Generator) -> GaussianState:
    return GaussianState(
        means=torch.randn(count, 3, generator=generator),
        log_scales=torch.randn(count, 3, generator=generator) - 3,
        rotations=torch.randn(count, 4, generator=generator),
        opacity_logits=torch.randn(count, 1, generator=generator),
        shs=torch.randn(count, 16, 3, generator=generator),
    )


@pytest.mark.parametrize(
    "flags",
    [dict(), dict(no_do=False, no_dshs=False, apply_rotation=True), dict(no_dx=True, no_dr=True, defor_depth=2)],
    ids=["default", "all-heads-quaternion", "partial"],
)
def test_forward_matches_plain_4dgs_recipe(flags):
    """A state dict written by 4DGS's module loads strictly and gives the same deformation."""
    args = hidden_args(**flags)
    torch.manual_seed(0)
    plain = PlainDeformNetwork(args)  # stands for a 4DGS-written deformation.pth
    with torch.no_grad():
        for level in plain.deformation_net.grid.grids:
            for plane in level:
                plane.uniform_(0.2, 1.5)  # time planes too
        for p in plain.parameters():
            if p.dim() == 2 and p.requires_grad:
                p.mul_(3.0)  # larger weights: deltas well away from zero
    ours = DeformNetwork(args)
    load_deformation_state(ours, plain.state_dict(), "plain")
    PlainDeformNetwork(args).load_state_dict(ours.state_dict(), strict=True)  # and ours loads in 4DGS's
    ours.set_aabb([1.5, 2.0, 1.0], [-1.0, -2.5, -1.2])
    plain.deformation_net.grid.aabb.data.copy_(ours.deformation_net.grid.aabb)

    generator = torch.Generator().manual_seed(1)
    state = _state(300, generator)
    means = state.means.clone().requires_grad_()
    times = torch.rand(300, 1, generator=generator)
    out = ours(state.replace(means=means), times)
    ref = plain(means, state.log_scales, state.rotations, state.opacity_logits, state.shs, times)
    for mine, theirs in zip((out.means, out.log_scales, out.rotations, out.opacity_logits, out.shs), ref):
        torch.testing.assert_close(mine, theirs, rtol=1e-5, atol=1e-5)
    weights = [torch.randn(t.shape, generator=generator) for t in ref]
    loss_ours = sum((w * t).sum() for w, t in zip(weights, (out.means, out.log_scales, out.rotations,
                                                              out.opacity_logits, out.shs)))
    loss_plain = sum((w * t).sum() for w, t in zip(weights, ref))
    params_ours = [means] + [p for p in ours.parameters() if p.requires_grad]
    params_plain = [means] + [p for p in plain.parameters() if p.requires_grad]
    grads_ours = torch.autograd.grad(loss_ours, params_ours, allow_unused=True)
    grads_plain = torch.autograd.grad(loss_plain, params_plain, allow_unused=True)
    for mine, theirs in zip(grads_ours, grads_plain):
        if theirs is None:
            assert mine is None or torch.count_nonzero(mine) == 0
        else:
            torch.testing.assert_close(mine, theirs, rtol=1e-4, atol=1e-4)
    # The heads that do run move values away from the input.
    assert (out.means - state.means).abs().max() > 1e-3 or flags.get("no_dx")


def test_group_parameters_follow_4dgs_rules():
    net = DeformNetwork(hidden_args())
    names = {id(p): n for n, p in net.named_parameters()}
    mlp = [names[id(p)] for p in net.get_mlp_parameters()]
    grid = [names[id(p)] for p in net.get_grid_parameters()]
    assert grid[0] == "deformation_net.grid.aabb" and all("grid" in n for n in grid)
    assert mlp[-4:] == ["timenet.0.weight", "timenet.0.bias", "timenet.2.weight", "timenet.2.bias"]
    assert not any("grid" in n for n in mlp)
    assert len(mlp) + len(grid) == len(names)


def test_check_state_lists_offending_keys():
    net = DeformNetwork(hidden_args())
    state = net.state_dict()
    bad = dict(state)
    del bad["timenet.0.bias"]
    bad["deformation_net.extra.weight"] = torch.zeros(1)
    bad["deformation_net.feature_out.0.weight"] = torch.zeros(3, 3)
    with pytest.raises(ValueError) as err:
        check_deformation_state(net, bad, "some/deformation.pth")
    message = str(err.value)
    assert "some/deformation.pth" in message
    assert "missing: timenet.0.bias" in message
    assert "unexpected: deformation_net.extra.weight" in message
    assert "deformation_net.feature_out.0.weight [3, 3]" in message


def test_unsupported_options_and_bad_times_raise():
    with pytest.raises(ValueError, match="static_mlp"):
        DeformNetwork(hidden_args(static_mlp=True))
    net = DeformNetwork(hidden_args())
    state = _state(5, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="times must be"):
        net(state, torch.zeros(4, 1))
    sh1 = state.replace(shs=torch.zeros(5, 4, 3))
    with pytest.raises(ValueError, match="16 SH coefficients"):
        DeformNetwork(hidden_args(no_dshs=False))(sh1, torch.zeros(5, 1))
    assert DeformNetwork(hidden_args())(sh1, torch.zeros(5, 1)).shs is sh1.shs


def test_no_grid_uses_position_and_time():
    net = DeformNetwork(hidden_args(no_grid=True))
    assert net.deformation_net.feature_out[0].in_features == 4
    state = _state(6, torch.Generator().manual_seed(0))
    early = net(state, torch.zeros(6, 1)).means
    late = net(state, torch.ones(6, 1)).means
    assert not torch.allclose(early, late)


def _randomised(args, seed: int = 0) -> DeformNetwork:
    torch.manual_seed(seed)
    net = DeformNetwork(args)
    with torch.no_grad():
        for level in net.deformation_net.grid.grids:
            for plane in level:
                plane.uniform_(0.2, 1.5)
    return net


def test_position_scale_keeps_the_function_and_saves_effective_weights():
    args = hidden_args()
    net = _randomised(args)
    state, times = _state(40, torch.Generator().manual_seed(1)), torch.rand(40, 1)
    before = net(state, times)
    plain_state = {k: v.clone() for k, v in net.state_dict().items()}
    net.deformation_net.set_position_scale(36.0)
    after = net(state, times)
    torch.testing.assert_close(after.means, before.means, rtol=1e-5, atol=1e-6)
    assert net.deformation_net.pos_deform[3].weight.abs().max() < plain_state["deformation_net.pos_deform.3.weight"].abs().max()
    # the saved weights are the effective ones: 4DGS's module (scale 1) loads them and deforms alike
    saved = net.state_dict()
    torch.testing.assert_close(saved["deformation_net.pos_deform.3.weight"],
                               plain_state["deformation_net.pos_deform.3.weight"])
    plain = PlainDeformNetwork(args)
    plain.load_state_dict(saved, strict=True)
    ours_at_one = DeformNetwork(args)
    ours_at_one.load_state_dict(saved, strict=True)
    torch.testing.assert_close(ours_at_one(state, times).means, before.means, rtol=1e-5, atol=1e-6)
    # ... and a model already at another scale loads them into its own parametrisation
    other = DeformNetwork(args)
    other.deformation_net.set_position_scale(5.0)
    other.load_state_dict(saved, strict=True)
    torch.testing.assert_close(other(state, times).means, before.means, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="position_scale"):
        net.deformation_net.set_position_scale(0.0)


def test_position_scale_makes_the_branch_learn_alike_at_any_scene_scale():
    """The same fit at unit scale and at scale k (points, targets and position scale x k): Adam at the
    same rate gives k times the displacement (what the dynamic branch of a scene at scale 50 needs);
    without the position scale the scaled copy fits far less of the same motion in as many steps. The
    position head starts at zero, as ReFlow's dynamic branch does (its zero-initialised heads): a random
    start would be a different function at each scale."""
    args = hidden_args()
    k = 50.0
    generator = torch.Generator().manual_seed(3)
    state = _state(64, generator)
    times = torch.rand(64, 1, generator=generator)
    target = 0.05 * torch.randn(64, 3, generator=generator)

    def fit(scale: float, reparametrise: bool) -> torch.Tensor:
        net = _randomised(args, seed=4)
        torch.nn.init.zeros_(net.deformation_net.pos_deform[3].weight)
        torch.nn.init.zeros_(net.deformation_net.pos_deform[3].bias)
        low, high = state.means.min(0).values * scale, state.means.max(0).values * scale
        net.set_aabb(high, low)
        if reparametrise:
            net.deformation_net.set_position_scale(scale)
        scaled = state.replace(means=state.means * scale)
        start = net(scaled, times).means.detach()
        # eps as 4DGS's optimizer (1e-15): Adam's eps is the one scale-dependent term of the update
        optimizer = torch.optim.Adam(net.parameters(), lr=3e-3, eps=1e-15)
        for _ in range(40):
            optimizer.zero_grad()
            moved = net(scaled, times).means - start
            ((moved - scale * target) ** 2).mean().backward()
            optimizer.step()
        return (net(scaled, times).means - start).detach()

    unit = fit(1.0, True)
    assert float((unit - target).norm()) < 0.9 * float(target.norm())  # it learns something
    torch.testing.assert_close(fit(k, True), k * unit, rtol=1e-3, atol=1e-4 * k * float(unit.abs().max()))
    slow = fit(k, False)
    residual_unit = float((unit - target).norm() / target.norm())
    residual_slow = float((slow - k * target).norm() / (k * target).norm())
    assert residual_slow > residual_unit + 0.2  # measured: 0.92 vs 0.59 of the motion left unfitted
