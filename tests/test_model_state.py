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


def test_runaway_log_scales_activate_to_finite_scales_with_finite_gradients():
    """exp(100) is inf in float32; the activation caps the log-scale at MAX_LOG_SCALE (the clamped
    axis gets no gradient, the others their exp)."""
    from baselines.fourdgs.state import MAX_LOG_SCALE

    state = _state(2)
    log_scales = torch.tensor([[100.0, -19.0, 1.0], [0.5, 0.5, 0.5]], requires_grad=True)
    state = state.replace(log_scales=log_scales)
    scales = state.scales
    assert torch.isfinite(scales).all()
    assert float(scales[0, 0]) == pytest.approx(math.exp(MAX_LOG_SCALE), rel=1e-6)
    torch.testing.assert_close(scales[1].detach(), torch.full((3,), math.exp(0.5)))
    scales.sum().backward()
    assert torch.isfinite(log_scales.grad).all() and log_scales.grad[0, 0] == 0.0
    assert float(log_scales.grad[0, 2]) == pytest.approx(math.e, rel=1e-6)


def test_a_deformation_that_runs_away_renders_finite_images_and_gradients():
    """The failure seen on DAVIS motocross-jump: the scale head adds +100 to the log-scales at a time
    (exp = inf), which stopped the run with "scales contains NaN or inf". Rendering stays finite."""
    from _model_helpers import make_model
    from baselines.data.cameras import Camera
    from baselines.fourdgs.renderer import composite_view, prepare_view

    model = make_model(count=30)
    with torch.no_grad():
        model._deformation.deformation_net.scales_deform[3].bias[0] += 100.0
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[40.0, 0, 24.0], [0, 40.0, 24.0], [0, 0, 1]])
    camera = Camera(uid=0, image_name="c", width=48, height=48, K=K, viewmat=viewmat, time=0.5)
    view = prepare_view(model, camera, "fine", "cpu")
    assert float(view.state.log_scales[:, 0].min()) > 50.0  # the runaway is really there
    image = composite_view(view, torch.zeros(3), None, "cpu").image
    assert torch.isfinite(image).all()
    image.sum().backward()
    for name, parameter in [("xyz", model._xyz), ("opacity", model._opacity), ("features", model._features_dc),
                            *model._deformation.named_parameters()]:
        assert parameter.grad is None or torch.isfinite(parameter.grad).all(), name
    assert model._xyz.grad is not None and model._opacity.grad is not None
