"""Dense reference compositor: every pixel against every visible Gaussian, in plain torch.

This is the test oracle for the tiled backends. It has no tiles, no bounding boxes and no early
exit loop; the rules (alpha clamp and threshold, transmittance stop) are written as whole-tensor
operations that can be read against DESIGN.md section 3 line by line. Autograd provides the
gradients. Memory is O(pixels x Gaussians), so it is for small scenes only.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .projection import ALPHA_THRESHOLD, Projection

ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
_MAX_PAIRS_PER_CHUNK = 1 << 22  # pixel x Gaussian pairs materialised at once


def pixel_centres(width: int, height: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[H*W, 2] (x, y) pixel centres in row-major order: pixel (i, j) -> (j + 0.5, i + 0.5)."""
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device) + 0.5,
        torch.arange(width, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    return torch.stack([xs, ys], dim=-1).reshape(-1, 2)


def composite_pixels(
    pixels: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor
) -> tuple[Tensor, Tensor]:
    """Front-to-back alpha compositing of depth-sorted Gaussians at given pixel centres.

    Args:
        pixels: [P, 2] pixel centres (x, y).
        means2d: [M, 2], conics: [M, 3], opacities: [M], features: [M, C], already sorted
            front to back.
    Returns:
        (features [P, C], alpha [P, 1]).
    """
    d = pixels[:, None, :] - means2d[None, :, :]  # [P, M, 2]
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-sigma), max=ALPHA_MAX)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_THRESHOLD), alpha, torch.zeros_like(alpha))
    # A pixel stops *before* the Gaussian that would bring transmittance to <= 1e-4. The running
    # product is non-increasing, so "before the first failure" is exactly "product still > 1e-4".
    with torch.no_grad():
        keep = torch.cumprod(1.0 - alpha, dim=1) > TRANSMITTANCE_MIN
    alpha = alpha * keep
    transmittance_after = torch.cumprod(1.0 - alpha, dim=1)
    transmittance_before = torch.cat([torch.ones_like(alpha[:, :1]), transmittance_after[:, :-1]], dim=1)
    weights = alpha * transmittance_before  # [P, M]
    return weights @ features, weights.sum(dim=1, keepdim=True)


def composite_reference(
    projection: Projection, opacities: Tensor, features: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Dense compositing of all visible Gaussians, sorted by depth (stable: ties keep index order).

    Args:
        projection: output of the projection stage for N Gaussians.
        opacities: [N] activated opacities. features: [N, C].
    Returns:
        (image [H, W, C] without background, alpha [H, W, 1]).
    """
    channels = features.shape[1]
    ids = torch.nonzero(projection.visible, as_tuple=False).squeeze(1)
    order = torch.sort(projection.depths.detach()[ids], stable=True).indices
    ids = ids[order]
    means2d = projection.means2d[ids]
    conics = projection.conics[ids]
    opac = opacities[ids]
    feats = features[ids]

    pixels = pixel_centres(width, height, means2d.dtype, means2d.device)
    n_pix = pixels.shape[0]
    chunk = max(1, _MAX_PAIRS_PER_CHUNK // max(1, ids.numel()))
    out_feat, out_alpha = [], []
    for start in range(0, n_pix, chunk):
        f, a = composite_pixels(pixels[start : start + chunk], means2d, conics, opac, feats)
        out_feat.append(f)
        out_alpha.append(a)
    image = torch.cat(out_feat, dim=0).reshape(height, width, channels)
    alpha = torch.cat(out_alpha, dim=0).reshape(height, width, 1)
    return image, alpha
