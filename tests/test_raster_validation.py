"""Bad inputs raise one ValueError naming the culprit, before any work."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.render import available_backends, composite, project_gaussians, rasterize
from raster_cases import project, random_scene


@pytest.fixture(scope="module")
def scene():
    return random_scene(20, 24, 18, channels=3, seed=0)


def _args(scene, **overrides):
    args = dict(means=scene.means, quats=scene.quats, scales=scene.scales, opacities=scene.opacities,
                features=scene.features, viewmat=scene.viewmat, K=scene.K, width=scene.width, height=scene.height)
    args.update(overrides)
    return args


def _raises(culprit: str, fn=rasterize, **kwargs):
    with pytest.raises(ValueError, match=culprit):
        fn(**kwargs)


def test_valid_inputs_render(scene):
    image, depth, alpha, meta = rasterize(**_args(scene, width=np.int64(24)))
    assert image.shape == (18, 24, 3)


@pytest.mark.parametrize("name, bad", [
    ("means", lambda s: s.means[:, :2]),
    ("means", lambda s: s.means.to(torch.int64)),
    ("quats", lambda s: s.quats[:, :3]),
    ("scales", lambda s: s.scales[:-1]),
    ("opacities", lambda s: s.opacities[:, None]),
    ("features", lambda s: s.features[:, 0]),
    ("features", lambda s: s.features[:, :0]),
    ("features", lambda s: s.features[:-2]),
    ("viewmat", lambda s: s.viewmat[:3]),
    ("K", lambda s: s.K[:2]),
    ("quats", lambda s: s.quats.tolist()),
])
def test_wrong_shapes_and_types(scene, name, bad):
    _raises(name, **_args(scene, **{name: bad(scene)}))


@pytest.mark.parametrize("name", ["quats", "scales", "opacities", "features", "viewmat", "K"])
def test_wrong_dtype(scene, name):
    value = _args(scene)[name]
    _raises(name, **_args(scene, **{name: value.double()}))


def test_float16_is_rejected_naming_the_culprit(scene):
    # float16 overflows in the projection (a near Gaussian's covariance exceeds 65504 px^2);
    # bfloat16 has float32's range and renders.
    half = {k: v.half() for k, v in _args(scene).items() if isinstance(v, torch.Tensor)}
    _raises("means is float16", **_args(scene, **half))
    proj = project(scene)
    proj.means2d = proj.means2d.half()
    _raises("projection.means2d is float16", composite, projection=proj, opacities=scene.opacities.half(),
            features=scene.features.half(), width=24, height=18)
    bf16 = {k: v.bfloat16() for k, v in _args(scene).items() if isinstance(v, torch.Tensor)}
    image, _, alpha, meta = rasterize(**_args(scene, **bf16), backend="cpu")
    assert image.dtype == torch.bfloat16 and bool(torch.isfinite(image).all()) and meta.visible.any()


@pytest.mark.parametrize("name", ["quats", "scales", "opacities", "features", "viewmat", "K"])
def test_wrong_device(scene, name):
    value = _args(scene)[name]
    _raises(name, **_args(scene, **{name: torch.empty(value.shape, dtype=value.dtype, device="meta")}))


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "features", "viewmat", "K"])
@pytest.mark.parametrize("bad_value", [float("nan"), float("inf")])
def test_non_finite_inputs(scene, name, bad_value):
    value = _args(scene)[name].clone()
    value.view(-1)[1] = bad_value
    _raises(name, **_args(scene, **{name: value}))


@pytest.mark.parametrize("bad_value", [float("nan"), float("-inf")])
def test_non_finite_background(scene, bad_value):
    _raises("background", **_args(scene), background=torch.tensor([0.0, bad_value, 1.0]))


def test_background_with_wrong_channels(scene):
    _raises("background", **_args(scene), background=torch.zeros(4))


def test_out_of_range_activated_values(scene):
    _raises("scales", **_args(scene, scales=scene.scales - 1.0))
    _raises("opacities", **_args(scene, opacities=scene.opacities + 1.0))
    K = scene.K.clone()
    K[0, 0] = 0.0
    _raises("K", **_args(scene, K=K))


@pytest.mark.parametrize("name", ["width", "height"])
@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "10", None, torch.tensor(16.0)])
def test_bad_image_size(scene, name, bad):
    _raises(name, **_args(scene, **{name: bad}))


def test_unknown_backend(scene):
    _raises("backend", **_args(scene), backend="cuda")


def test_gsplat_without_cuda_is_a_clear_error(scene):
    _raises("gsplat.*CUDA", **_args(scene), backend="gsplat")
    assert "gsplat" not in available_backends("cpu")


def test_stage_functions_validate_too(scene):
    kwargs = dict(means=scene.means, quats=scene.quats, scales=scene.scales, viewmat=scene.viewmat, K=scene.K,
                  width=24, height=18)
    _raises("scales", project_gaussians, **{**kwargs, "scales": scene.scales[:, :2]})
    _raises("height", project_gaussians, **{**kwargs, "height": 0})
    proj = project(scene)
    ok = dict(projection=proj, opacities=scene.opacities, features=scene.features, width=24, height=18)
    nan_features = scene.features.clone()
    nan_features[0, 0] = float("nan")
    _raises("features", composite, **{**ok, "features": nan_features})
    _raises("opacities", composite, **{**ok, "opacities": scene.opacities.double()})
    _raises("opacities", composite, **{**ok, "opacities": scene.opacities[:-1]})
    _raises("projection", composite, **{**ok, "projection": {"means2d": proj.means2d}})
    _raises("backend", composite, **ok, backend="nope")
    image, depth, alpha = composite(**ok, backend="cpu")
    assert image.shape == (18, 24, 3)
