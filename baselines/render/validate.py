"""Input validation for the rasterizer: one ValueError naming the offending argument.

Validation runs before any work so that nothing silently produces a NaN image. It costs one pass
over the inputs (an isfinite reduction per tensor), negligible next to rasterization.
"""
from __future__ import annotations

import operator

import torch
from torch import Tensor


def _require_tensor(name: str, value: object) -> Tensor:
    if not isinstance(value, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def _require_shape(name: str, value: Tensor, shape: tuple[int | None, ...], meaning: str) -> None:
    ok = value.dim() == len(shape) and all(s is None or s == v for s, v in zip(shape, value.shape))
    if not ok:
        raise ValueError(f"{name} must have shape {meaning}, got {tuple(value.shape)}")


def require_image_size(width: object, height: object) -> tuple[int, int]:
    """Check that width and height are positive Python/NumPy integers; return them as int."""
    sizes = []
    for name, v in (("width", width), ("height", height)):
        try:
            # operator.index accepts only integer-like values (int, NumPy integers, integer 0-d
            # tensors); bool is rejected explicitly because True would silently mean 1 pixel.
            size = None if isinstance(v, bool) else operator.index(v)  # type: ignore[arg-type]
        except TypeError:
            size = None
        if size is None or size <= 0:
            raise ValueError(f"{name} must be a positive integer, got {v!r}")
        sizes.append(int(size))
    return sizes[0], sizes[1]


def validate_camera(viewmat: object, K: object, reference: Tensor) -> None:
    """Check viewmat [4,4] and K [3,3]: tensors of the reference's dtype/device, finite, fx, fy > 0."""
    for name, value, shape, meaning in (("viewmat", viewmat, (4, 4), "[4, 4]"), ("K", K, (3, 3), "[3, 3]")):
        t = _require_tensor(name, value)
        _require_shape(name, t, shape, meaning)
        _require_same_kind(name, t, reference)
        _require_finite(name, t)
    if not (float(K[0, 0]) > 0 and float(K[1, 1]) > 0):  # type: ignore[index]
        raise ValueError(f"K must have positive focal lengths, got fx={float(K[0, 0])}, fy={float(K[1, 1])}")  # type: ignore[index]


def _require_same_kind(name: str, value: Tensor, reference: Tensor) -> None:
    if value.dtype != reference.dtype:
        raise ValueError(f"{name} has dtype {value.dtype} but means has {reference.dtype}; use one floating dtype")
    if value.device != reference.device:
        raise ValueError(f"{name} is on {value.device} but means is on {reference.device}; use one device")


def _require_supported_float(name: str, value: Tensor) -> None:
    if not value.is_floating_point():
        raise ValueError(f"{name} must be a floating tensor, got {value.dtype}")
    if value.dtype == torch.float16:
        # Screen-space covariances scale with (focal / z)^2: 0.1 in front of a 500 px focal
        # camera that factor is 2.5e7 px^2 per unit of 3D variance, beyond float16's 65504.
        raise ValueError(f"{name} is float16, which the rasterizer does not support (screen-space covariances "
                         "overflow its range, max 65504); use float32, float64 or bfloat16")


def _require_finite(name: str, value: Tensor) -> None:
    if value.numel() and not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} contains NaN or inf")


def validate_gaussians(
    means: object, quats: object, scales: object, opacities: object = None, features: object = None
) -> int:
    """Check the per-Gaussian inputs; return N.

    means [N,3] floating; quats [N,4]; scales [N,3] >= 0 (activated); opacities [N] in [0,1]
    (activated); features [N,C] with C >= 1. Same dtype and device, all finite. opacities and
    features are optional (the projection stage needs neither).
    """
    m = _require_tensor("means", means)
    _require_supported_float("means", m)
    _require_shape("means", m, (None, 3), "[N, 3]")
    n = m.shape[0]
    checks = [
        ("quats", quats, (n, 4), "[N, 4] (w, x, y, z)"),
        ("scales", scales, (n, 3), "[N, 3]"),
        ("opacities", opacities, (n,), "[N]"),
        ("features", features, (n, None), "[N, C]"),
    ]
    present = [(name, v, shape, meaning) for name, v, shape, meaning in checks
               if v is not None or name in ("quats", "scales")]
    for name, value, shape, meaning in present:
        t = _require_tensor(name, value)
        _require_shape(name, t, shape, f"{meaning} with N={n}")
        _require_same_kind(name, t, m)
    if features is not None and features.shape[1] < 1:  # type: ignore[union-attr]
        raise ValueError("features must have at least one channel, got C=0")
    _require_finite("means", m)
    for name, value, _, _ in present:
        _require_finite(name, value)  # type: ignore[arg-type]
    if n and bool((scales < 0).any()):  # type: ignore[operator]
        raise ValueError("scales must be non-negative activated scales (did you pass log-scales?)")
    if n and opacities is not None and bool(((opacities < 0) | (opacities > 1)).any()):  # type: ignore[operator]
        raise ValueError("opacities must lie in [0, 1] (activated values; did you pass logits?)")
    return n


def validate_background(background: object, channels: int, reference: Tensor) -> None:
    """Check an optional background [C] matching the feature channels."""
    if background is None:
        return
    t = _require_tensor("background", background)
    _require_shape("background", t, (channels,), f"[C] with C={channels}")
    _require_same_kind("background", t, reference)
    _require_finite("background", t)


def validate_composite_inputs(means2d: Tensor, n: int, opacities: object, features: object) -> None:
    """Check the compositing stage's per-Gaussian inputs against a projection of N Gaussians.

    opacities [N] in [0, 1] and features [N, C] (C >= 1): tensors of means2d's dtype and device,
    all finite.
    """
    _require_supported_float("projection.means2d", means2d)
    for name, value, shape, meaning in (("opacities", opacities, (n,), "[N]"), ("features", features, (n, None), "[N, C]")):
        t = _require_tensor(name, value)
        _require_shape(name, t, shape, f"{meaning} with N={n} (the projection's Gaussian count)")
        if t.dtype != means2d.dtype:
            raise ValueError(f"{name} has dtype {t.dtype} but the projection has {means2d.dtype}; use one floating dtype")
        if t.device != means2d.device:
            raise ValueError(f"{name} is on {t.device} but the projection is on {means2d.device}; use one device")
        _require_finite(name, t)
    if features.shape[1] < 1:  # type: ignore[union-attr]
        raise ValueError("features must have at least one channel, got C=0")
    if n and bool(((opacities < 0) | (opacities > 1)).any()):  # type: ignore[operator]
        raise ValueError("opacities must lie in [0, 1] (activated values; did you pass logits?)")
