"""Public rasterizer API: validation, stage dispatch, depth and background handling.

    rasterize(means, quats, scales, opacities, features, viewmat, K, width, height,
              backend="auto", background=None) -> (features_img [H,W,C], depth [H,W,1],
                                                   alpha [H,W,1], meta: RasterMeta)

Backends only composite features; expected depth is composited as one extra channel in the same
pass (so every map of a view comes from ONE rasterization) and normalised here:
depth = sum(w z) / max(alpha, 1e-10). The background is blended here as (1 - alpha) * background.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .backends import resolve_backend
from .projection import Projection
from .validate import (
    require_image_size, validate_background, validate_camera, validate_composite_inputs, validate_gaussians,
)

DEPTH_EPS = 1e-10


@dataclass
class RasterMeta(Projection):
    """Projection of the rendered Gaussians plus what produced the image.

    Attributes (in addition to Projection's means2d, cov2d, conics, depths, radii, visible):
        backend: the backend that actually ran ("reference", "cpu", "gsplat").
        width, height: image size.
    `means2d.grad` (pixel units) is populated by backward when means2d requires grad.
    """

    backend: str = ""
    width: int = 0
    height: int = 0


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    opacities: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    backend: str = "auto",
) -> Projection:
    """Projection stage alone (see projection.Projection for the outputs).

    Args:
        means [N,3], quats [N,4] wxyz, scales [N,3] activated, viewmat [4,4] world-to-camera,
        K [3,3], width, height; opacities [N] (optional) tighten the bounding boxes.
    """
    width, height = require_image_size(width, height)
    validate_gaussians(means, quats, scales, opacities)
    validate_camera(viewmat, K, means)
    return resolve_backend(backend, means.device).project(
        means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d
    )


def composite(
    projection: Projection,
    opacities: Tensor,
    features: Tensor,
    width: int,
    height: int,
    backend: str = "auto",
    background: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Compositing stage alone: features, expected depth and alpha images.

    Args:
        projection: from `project_gaussians` for the same N Gaussians and camera.
        opacities: [N] activated. features: [N, C]. background: optional [C].
    Returns:
        (features_img [H, W, C], depth [H, W, 1], alpha [H, W, 1]).
    """
    width, height = require_image_size(width, height)
    if not isinstance(projection, Projection):
        raise ValueError(f"projection must be a Projection (from project_gaussians), got {type(projection).__name__}")
    validate_composite_inputs(projection.means2d, projection.depths.shape[0], opacities, features)
    validate_background(background, features.shape[1], features)
    return _composite(resolve_backend(backend, features.device), projection, opacities, features, width, height, background)


def _composite(backend, projection, opacities, features, width, height, background):
    channels = features.shape[1]
    with_depth = torch.cat([features, projection.depths.unsqueeze(1).to(features.dtype)], dim=1)
    image, alpha = backend.composite(projection, opacities, with_depth, width, height)
    feats = image[..., :channels]
    depth = image[..., channels:] / torch.clamp(alpha, min=DEPTH_EPS)
    if background is not None:
        feats = feats + (1.0 - alpha) * background
    return feats, depth, alpha


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    backend: str = "auto",
    background: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, RasterMeta]:
    """Render N Gaussians with arbitrary feature channels into one view.

    Args:
        means: [N, 3] world positions. quats: [N, 4] wxyz (normalised inside).
        scales: [N, 3] activated scales. opacities: [N] activated opacities in [0, 1].
        features: [N, C] per-Gaussian features (RGB, flow coefficients, ...), C >= 1.
        viewmat: [4, 4] world-to-camera, OpenCV axes. K: [3, 3] intrinsics in pixels.
        width, height: image size. backend: "auto" | "reference" | "cpu" | "gsplat".
        background: optional [C] blended where alpha < 1.
    Returns:
        features_img [H, W, C], depth [H, W, 1] (expected camera z), alpha [H, W, 1], meta.
    Raises:
        ValueError naming the argument for wrong shapes/dtypes/devices, NaN/inf, bad sizes, or
        an unusable backend.
    """
    width, height = require_image_size(width, height)
    validate_gaussians(means, quats, scales, opacities, features)
    validate_camera(viewmat, K, means)
    validate_background(background, features.shape[1], means)
    chosen = resolve_backend(backend, means.device)
    proj = chosen.project(means, quats, scales, viewmat, K, width, height, opacities, 0.01, 1e10, 0.3)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    feats, depth, alpha = _composite(chosen, proj, opacities, features, width, height, background)
    meta = RasterMeta(
        means2d=proj.means2d, cov2d=proj.cov2d, conics=proj.conics, depths=proj.depths,
        radii=proj.radii, visible=proj.visible, backend=chosen.name, width=width, height=height,
    )
    return feats, depth, alpha, meta
