"""The deformation MLP's number format (`--mlp_precision`): bfloat16 autocast close to float32,
float32 untouched, the automatic choice following the CPU's native bfloat16 support."""

import pytest
import torch

import baselines.fourdgs.deformation as deformation
from baselines.fourdgs.deformation import DeformNetwork, mlp_autocast
from baselines.fourdgs.state import GaussianState
from tests._model_helpers import hidden_args


def _state(count: int, dtype=torch.float32, seed: int = 0) -> tuple[GaussianState, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    state = GaussianState(
        means=torch.rand(count, 3, generator=g, dtype=dtype) * 2 - 1,
        log_scales=torch.randn(count, 3, generator=g, dtype=dtype),
        rotations=torch.randn(count, 4, generator=g, dtype=dtype),
        opacity_logits=torch.randn(count, 1, generator=g, dtype=dtype),
        shs=torch.randn(count, 16, 3, generator=g, dtype=dtype),
    )
    return state, torch.rand(count, 1, generator=g, dtype=dtype)


def _networks(**overrides) -> tuple[DeformNetwork, DeformNetwork]:
    """Two networks with the same weights: float32 and bfloat16 matrix products."""
    torch.manual_seed(0)
    reference = DeformNetwork(hidden_args(net_width=64, **overrides, mlp_precision="float32"))
    low = DeformNetwork(hidden_args(net_width=64, **overrides, mlp_precision="bfloat16"))
    low.load_state_dict(reference.state_dict())
    return reference, low


def _deltas(net: DeformNetwork, state: GaussianState, times: torch.Tensor) -> torch.Tensor:
    out = net(state, times)
    return torch.cat([out.means - state.means, out.log_scales - state.log_scales, out.rotations - state.rotations], 1)


def test_bfloat16_deltas_are_close_to_float32_and_stay_float32():
    reference, low = _networks()
    state, times = _state(500)
    expected, got = _deltas(reference, state, times), _deltas(low, state, times)
    assert got.dtype == torch.float32 and all(p.dtype == torch.float32 for p in low.parameters())
    scale = expected.abs().max()
    error = (got - expected).abs().max() / scale
    # bfloat16 keeps 8 significant bits (relative spacing 2^-8 = 0.4%); a few products in a row
    assert 1e-5 < error < 3e-2, error  # > 1e-5: the low-precision path really ran


def test_bfloat16_gradients_point_where_float32_ones_do():
    reference, low = _networks()
    state, times = _state(500)
    target = torch.randn(500, 10, generator=torch.Generator().manual_seed(1))
    grads = []
    for net in (reference, low):
        net.zero_grad()
        ((_deltas(net, state, times) - target) ** 2).mean().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters() if p.grad is not None]))
    assert all(torch.isfinite(g).all() for g in grads)
    cosine = torch.nn.functional.cosine_similarity(grads[0], grads[1], dim=0)
    assert cosine > 0.99, cosine


def test_float32_and_auto_without_native_bfloat16_are_exactly_4dgs(monkeypatch):
    reference, _ = _networks()
    state, times = _state(200)
    expected = _deltas(reference, state, times)
    monkeypatch.setattr(deformation, "native_bfloat16_cpu", lambda: False)
    auto = DeformNetwork(hidden_args(net_width=64, mlp_precision="auto"))
    auto.load_state_dict(reference.state_dict())
    assert torch.equal(_deltas(auto, state, times), expected)


def test_auto_uses_bfloat16_where_the_cpu_has_it(monkeypatch):
    monkeypatch.setattr(deformation, "native_bfloat16_cpu", lambda: True)
    assert mlp_autocast("auto", torch.device("cpu")).fast_dtype == torch.bfloat16
    assert mlp_autocast("auto", torch.device("cpu"))._enabled
    assert not mlp_autocast("float32", torch.device("cpu"))._enabled
    monkeypatch.setattr(deformation, "native_bfloat16_cpu", lambda: False)
    assert not mlp_autocast("auto", torch.device("cpu"))._enabled


def test_a_float64_model_keeps_float64_outputs():
    net = DeformNetwork(hidden_args(net_width=16, mlp_precision="float32")).double()
    state, times = _state(50, dtype=torch.float64)
    assert net(state, times).means.dtype == torch.float64


def test_an_unknown_precision_is_refused_at_construction():
    with pytest.raises(ValueError, match="mlp_precision"):
        DeformNetwork(hidden_args(mlp_precision="float16"))
