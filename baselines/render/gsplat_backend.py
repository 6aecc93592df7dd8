"""gsplat backend: the two rasterizer stages on CUDA through gsplat's stage functions.

    project_gaussians_gsplat(...) -> Projection      gsplat.fully_fused_projection
    composite_gsplat(...) -> (image, alpha)          gsplat.isect_tiles, isect_offset_encode,
                                                     rasterize_to_pixels

gsplat implements the same rules as the torch backends (docs/ARCHITECTURE.md), so results agree
up to float32 rounding. Supported: gsplat >= 1.4. Differences between releases handled here:

- radii are [C, N, 2] per-axis half-extents from 1.5 on, [C, N] (one isotropic 3-sigma radius,
  without the opacity-aware tightening) before. 1.4's radii are widened to [N, 2] here; its boxes
  drop the faint fringe between 3 and 3.33 standard deviations, so install gsplat >= 1.5 for
  results that match the cpu backend at the 1/255 level.
- `fully_fused_projection(opacities=...)` exists from 1.5 on; it is passed only where accepted.

gsplat allocates its per-Gaussian outputs without initialising culled entries, so every value of
an invisible Gaussian is replaced by what the torch projection computes for it (`fill_culled`:
true off-screen or faded-out projections, finite stand-ins behind the near plane). gsplat
computes in float32 only; other dtypes are rejected with a ValueError.

This module is imported only when the gsplat backend is selected (see backends.py), so importing
the rasterizer never imports gsplat.
"""
from __future__ import annotations

import importlib
import inspect
import math
import re
from types import ModuleType

import torch
from torch import Tensor

from .projection import Projection, project_gaussians_torch
from .tiles import TILE_SIZE

# Channels per rasterize_to_pixels call. gsplat accepts up to 513 (padding to its instantiated
# counts), but its backward kernel keeps 16 x 16 x (28 + 4 C) bytes of shared memory per tile: 531 kB
# at C = 512, more than any GPU has (an H200 crashed on it). At 32: 40 kB, under the 48 kB every
# CUDA GPU gives without opting in. Training renders at most 12 channels, in one call.
MAX_CHANNELS_PER_CALL = 32


def _gsplat() -> ModuleType:
    return importlib.import_module("gsplat")


def _version(module: ModuleType) -> tuple[int, int]:
    match = re.match(r"(\d+)\.(\d+)", str(getattr(module, "__version__", "0.0")))
    return (int(match.group(1)), int(match.group(2))) if match else (0, 0)


def _per_axis_radii(module: ModuleType) -> bool:
    """True when this gsplat returns and expects radii [..., N, 2] (gsplat >= 1.5)."""
    return _version(module) >= (1, 5)


def _require_float32(name: str, tensor: Tensor) -> None:
    if tensor.dtype != torch.float32:
        raise ValueError(f"backend='gsplat' computes in float32, but {name} has dtype {tensor.dtype}")


def project_gaussians_gsplat(
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
) -> Projection:
    """EWA projection of N Gaussians with gsplat.fully_fused_projection (one camera).

    Args and returns as projection.project_gaussians_torch. Gradients flow to means, quats and
    scales through gsplat's backward (means2d, conics) and through torch (depths).
    """
    _require_float32("means", means)
    if means.shape[0] == 0:  # gsplat's kernels crash on zero Gaussians (seen on an H200)
        return project_gaussians_torch(means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d)
    gsplat = _gsplat()
    project = gsplat.fully_fused_projection
    kwargs = {}
    if opacities is not None and "opacities" in inspect.signature(project).parameters:
        kwargs["opacities"] = opacities.detach().contiguous()  # only tightens the boxes
    radii, means2d, _, conics, _ = project(
        means.contiguous(), None, quats.contiguous(), scales.contiguous(), viewmat[None].contiguous(),
        K[None].contiguous(), int(width), int(height), eps2d=eps2d, near_plane=near, far_plane=far, **kwargs,
    )
    radii, means2d, conics = radii[0], means2d[0], conics[0]  # drop the camera dimension
    if radii.dim() == 1:  # gsplat < 1.5: one isotropic radius per Gaussian
        radii = radii[:, None].expand(-1, 2)
    radii = radii.to(torch.int32)
    visible = (radii > 0).any(dim=-1)
    if opacities is not None and not kwargs:  # gsplat < 1.5 does not cull faint Gaussians itself
        visible = visible & (opacities.detach() >= 1.0 / 255.0)
    radii = radii * visible[:, None]
    means2d, conics, cov2d = fill_culled(means2d, conics, visible, means, quats, scales, viewmat, K, width, height,
                                         near, far, eps2d)
    depths = (means @ viewmat[2, :3]) + viewmat[2, 3]  # camera-space z, defined for every Gaussian
    return Projection(means2d=means2d, cov2d=cov2d, conics=conics, depths=depths, radii=radii, visible=visible)


def fill_culled(means2d: Tensor, conics: Tensor, visible: Tensor, means: Tensor, quats: Tensor, scales: Tensor,
                viewmat: Tensor, K: Tensor, width: int, height: int, near: float = 0.01, far: float = 1e10,
                eps2d: float = 0.3) -> tuple[Tensor, Tensor, Tensor]:
    """(means2d [N, 2], conics [N, 3], cov2d [N, 2, 2]): gsplat's values where `visible`, the torch
    projection's for every culled Gaussian.

    gsplat leaves culled entries uninitialised. Their true values still matter: a Gaussian off the
    image or faded out (opacity below 1/255) in view b is where view a's pixels flow to (ReFlow's
    full flow reads view b's means and covariances of every Gaussian in front of camera b); a
    placeholder (the principal point) would send them to the image centre. The torch projection
    computes them (and finite stand-ins behind the near plane), so both backends agree.
    """
    culled = (~visible).nonzero()[:, 0]
    a, b, c = conics.unbind(-1)
    cov2d = torch.stack([c, -b, -b, a], dim=-1).reshape(-1, 2, 2) / (a * c - b * b)[:, None, None]
    if culled.numel() == 0:
        return means2d, conics, cov2d
    sub = project_gaussians_torch(means[culled], quats[culled], scales[culled], viewmat, K, width, height,
                                  near=near, far=far, eps2d=eps2d)
    index = (culled,)
    return (means2d.index_put(index, sub.means2d.to(means2d.dtype)),
            conics.index_put(index, sub.conics.to(conics.dtype)),
            cov2d.index_put(index, sub.cov2d.to(cov2d.dtype)))


def composite_gsplat(
    projection: Projection, opacities: Tensor, features: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Tile intersection and compositing with gsplat (one camera).

    Args:
        projection: from any backend's projection stage (radii [N, 2] int32, visible).
        opacities: [N]. features: [N, C], any C >= 1 (split into calls of at most MAX_CHANNELS_PER_CALL channels).
    Returns:
        (image [H, W, C] without background, alpha [H, W, 1]).
    """
    _require_float32("features", features)
    width, height = int(width), int(height)
    if features.shape[0] == 0:  # nothing to draw (gsplat crashes on zero Gaussians); still in the graph
        tie = features.sum() + opacities.sum() + projection.means2d.sum() + projection.conics.sum()
        zeros = features.new_zeros((height, width, features.shape[1] + 1)) + 0.0 * tie
        return zeros[..., :-1], zeros[..., -1:]
    gsplat = _gsplat()
    tiles_x = math.ceil(width / TILE_SIZE)
    tiles_y = math.ceil(height / TILE_SIZE)
    radii = projection.radii.to(torch.int32) * projection.visible[:, None]
    if not _per_axis_radii(gsplat):
        radii = radii.amax(dim=-1)
    means2d = projection.means2d
    _, isect_ids, flatten_ids = gsplat.isect_tiles(
        means2d.detach()[None].contiguous(), radii[None].contiguous(),
        projection.depths.detach()[None].contiguous(), TILE_SIZE, tiles_x, tiles_y,
    )
    offsets = gsplat.isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    images, alpha = [], None
    for start in range(0, features.shape[1], MAX_CHANNELS_PER_CALL):
        chunk = features[:, start : start + MAX_CHANNELS_PER_CALL]
        image, chunk_alpha = gsplat.rasterize_to_pixels(
            means2d[None], projection.conics[None], chunk[None].contiguous(), opacities[None].contiguous(),
            width, height, TILE_SIZE, offsets, flatten_ids,
        )
        images.append(image[0])
        alpha = chunk_alpha[0] if alpha is None else alpha
    image = images[0] if len(images) == 1 else torch.cat(images, dim=-1)
    return image, alpha
