"""Backward warping, validity masks and the masked photometric loss of flow matching.

    warped, inside = backward_warp(image_b, flow_ab)        # image_b sampled at q + F_a->b(q)
    loss = photometric_loss(warped, image_a, mask)          # 0.8 L1 + 0.2 (1 - SSIM) on mask pixels

"Warp I_b to t_a and compare with I_a" is backward sampling on view a's pixel grid: the value at
pixel q is I_b at q + F_a->b(q) (bilinear, so the loss is differentiable in the flow). A sample is
`inside` when q + F lies in the image ([0, W] x [0, H] in pixel coordinates, centres at +0.5);
outside samples are masked, never extrapolated. Images are [H, W, C] float tensors.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from baselines.metrics import ssim_map

from .flow import pixel_grid


def backward_warp(image: Tensor, flow: Tensor) -> tuple[Tensor, Tensor]:
    """(image sampled at q + flow(q) [H, W, C], inside [H, W] bool).

    Args:
        image: [H, W, C] source image (view b). flow: [H, W, 2] (dx, dy) in pixels, finite.
    """
    h, w = flow.shape[:2]
    if image.shape[:2] != (h, w):
        raise ValueError(f"backward_warp: image {tuple(image.shape)} and flow {tuple(flow.shape)} sizes differ")
    target = pixel_grid(h, w, flow) + flow
    inside = (target[..., 0] >= 0) & (target[..., 0] <= w) & (target[..., 1] >= 0) & (target[..., 1] <= h)
    # grid_sample with align_corners=False addresses pixel centres at (2 * (j + 0.5) / W - 1).
    grid = torch.stack((2.0 * target[..., 0] / w - 1.0, 2.0 * target[..., 1] / h - 1.0), dim=-1)
    sampled = F.grid_sample(image.permute(2, 0, 1).unsqueeze(0), grid.unsqueeze(0).to(image.dtype),
                            mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[0].permute(1, 2, 0), inside


def photometric_losses(preds: Tensor, targets: Tensor, masks: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """[B] losses (1 - ssim_weight) L1 + ssim_weight (1 - SSIM), each averaged over its mask.

    Args:
        preds, targets: [B, H, W, C]. masks: [B, H, W] bool or float weights in [0, 1].
    Pixels outside a mask are replaced by the target before SSIM's 11x11 window sees them (so
    garbage there cannot leak in) and carry no gradient. An empty mask gives a zero that is
    still connected to the graph. One batched SSIM call for all B terms (the per-call overhead
    of the separable convolutions dominates at training resolutions).
    """
    weights = masks.to(preds.dtype).unsqueeze(-1)  # [B, H, W, 1]
    counts = weights.sum(dim=(1, 2, 3))  # [B]
    safe = counts.clamp_min(1.0)
    filled = torch.where(weights > 0, preds, targets)
    channels = preds.shape[-1]
    l1 = (weights * (filled - targets).abs()).sum(dim=(1, 2, 3)) / (safe * channels)
    loss = l1
    if ssim_weight != 0:
        ssim_values = ssim_map(filled, targets).mean(dim=-1, keepdim=True)
        d_ssim = 1.0 - (weights * ssim_values).sum(dim=(1, 2, 3)) / safe
        loss = (1.0 - ssim_weight) * l1 + ssim_weight * d_ssim
    return torch.where(counts >= 1.0, loss, (preds * 0.0).sum(dim=(1, 2, 3)))


def photometric_loss(pred: Tensor, target: Tensor, mask: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """One term of `photometric_losses`: pred, target [H, W, C], mask [H, W] -> scalar."""
    return photometric_losses(pred.unsqueeze(0), target.unsqueeze(0), mask.unsqueeze(0), ssim_weight)[0]


def gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """[H, W, C] image blurred with a separable Gaussian of `sigma` pixels (edge pixels repeated)."""
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = torch.arange(-radius, radius + 1, device=image.device, dtype=image.dtype)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()
    c = image.shape[-1]
    chw = F.pad(image.permute(2, 0, 1).unsqueeze(0), (radius, radius, radius, radius), mode="replicate")
    chw = F.conv2d(chw, kernel.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    chw = F.conv2d(chw, kernel.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return chw[0].permute(1, 2, 0)


def occlusion_mask(flow_ab: Tensor, flow_ba: Tensor, alpha1: float = 0.01, alpha2: float = 0.5) -> Tensor:
    """[H, W] bool: pixels of view a whose flow is forward-backward consistent (not occluded).

    Sundaram et al. (ECCV 2010): |f + b'|^2 < alpha1 (|f|^2 + |b'|^2) + alpha2, with b' = F_b->a
    sampled at q + F_a->b(q). Computed without gradient (a mask, not a loss).
    """
    with torch.no_grad():
        back, inside = backward_warp(flow_ba, flow_ab)
        lhs = (flow_ab + back).square().sum(-1)
        rhs = alpha1 * (flow_ab.square().sum(-1) + back.square().sum(-1)) + alpha2
        return (lhs < rhs) & inside
