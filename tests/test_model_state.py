"""GaussianState: activated views, cheap indexing/concatenation, shape validation."""

import math

import pytest
import torch

from baselines.fourdgs.state import GaussianState


def _state(count: int = 5) -> GaussianState:
    return GaussianState(
        means=torch.arange(count * 3, dtype=torch.float32).reshape(count, 3),
        log_scales=torch.full((count, 3), math.log(2.0)),
        rotations=torch.tensor([[2.0, 0.0, 0.0, 0.0]]).repeat(count, 1),
        opacity_logits=torch.zeros(count, 1),
        shs=torch.zeros(count, 16, 3),
    )


def test_activated_views():
    state = _state()
    torch.testing.assert_close(state.scales, torch.full((5, 3), 2.0))
    torch.testing.assert_close(state.quats, torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(5, 1))
    assert state.opacities.shape == (5,) and torch.all(state.opacities == 0.5)
    assert state.sh_degree == 3 and len(state) == 5


def test_index_and_cat():
    state = _state()
    sliced = state.index(slice(1, 3))
    assert sliced.means.data_ptr() == state.means[1:].data_ptr()  # a view, no copy
    masked = state.index(torch.tensor([True, False, True, False, False]))
    assert masked.means[:, 0].tolist() == [0.0, 6.0]
    picked = state.index([4, 0])
    assert picked.means[:, 0].tolist() == [12.0, 0.0]
    assert GaussianState.cat([state]) is state
    joined = GaussianState.cat([masked, picked])
    assert joined.means[:, 0].tolist() == [0.0, 6.0, 12.0, 0.0] and joined.shs.shape == (4, 16, 3)
    with pytest.raises(ValueError, match="bool mask"):
        state.index(torch.tensor([True, False]))


def test_validate_names_the_field():
    assert _state().validate().num_gaussians == 5
    with pytest.raises(ValueError, match="rotations"):
        _state().replace(rotations=torch.zeros(5, 3)).validate()
    with pytest.raises(ValueError, match="K=5"):
        _state().replace(shs=torch.zeros(5, 5, 3)).validate()
