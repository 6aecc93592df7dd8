"""Backward warping, validity masks and the masked photometric loss of flow matching.

    warped, inside = backward_warp(image_b, flow_ab)        # image_b sampled at q + F_a->b(q)
    loss = photometric_loss(warped, image_a, mask)          # 0.8 L1 + 0.2 (1 - SSIM) on mask pixels

"Warp I_b to t_a and compare with I_a" is backward sampling on view a's pixel grid: the value at
pixel q is I_b at q + F_a->b(q) (bilinear, so the loss is differentiable in the flow). A sample is
`inside` when q + F lies in the image ([0, W] x [0, H] in pixel coordinates, centres at +0.5);
outside samples are masked, never extrapolated. Images are [H, W, C] float tensors.

The masked photometric terms are evaluated on each mask's bounding box grown by SSIM's window
radius (`photometric_losses`): a mask pixel's SSIM reads only pixels within that radius, so the
crop gives it the same value (and the zero-padded border where the box meets the image edge),
and pixels outside the box carry no weight. Full flow matching masks the dynamic pixels only, so
6 of a ReFlow step's 8 terms shrink to the moving object's box. `photometric_losses_dense` (the
whole image) stays the oracle; `REFLOW4DGS_MASK_CROP=0` switches the crop off.
"""
from __future__ import annotations

import math
import os

import torch
import torch.nn.functional as F
from torch import Tensor

from baselines.metrics import SSIM_WINDOW, ssim_map
from baselines.native_build import OFF_VALUES

from .flow import pixel_grid

CROP_SWITCH = "REFLOW4DGS_MASK_CROP"  # 0/false/off/no: photometric terms on the whole image
CROP_MARGIN = SSIM_WINDOW // 2  # pixels SSIM reads on either side of the pixel it scores
# terms whose crop covers more than this share of the image are evaluated whole, batched together
# (a mask spread over the image, e.g. camera flow's static pixels, gains nothing from its box)
WHOLE_IMAGE_SHARE = 0.6


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
    still connected to the graph. Each term is evaluated on its mask's box grown by CROP_MARGIN
    (clipped to the image): the small boxes batched in one SSIM call at their largest size, the
    large ones (all, when that size is most of the image) in another on the whole image. Values
    and gradients are those of `photometric_losses_dense` up to the order of the final sums.
    """
    if os.environ.get(CROP_SWITCH, "").strip().lower() in OFF_VALUES:
        return photometric_losses_dense(preds, targets, masks, ssim_weight)
    b, h, w = masks.shape
    weights = masks.to(preds.dtype).unsqueeze(-1)  # [B, H, W, 1]
    counts = weights.sum(dim=(1, 2, 3))  # [B]
    boxes, totals = mask_boxes(weights[..., 0] > 0), counts.tolist()
    whole, cropped, empty = [], [], []
    for k, box in enumerate(boxes):
        if box is None or totals[k] < 1.0:
            empty.append(k)  # its loss is the connected zero below
        else:
            y0, y1, x0, x1 = _grown(box, h, w)
            (whole if (y1 - y0) * (x1 - x0) > WHOLE_IMAGE_SHARE * h * w else cropped).append(k)
    if cropped:
        spans = [_grown(boxes[k], h, w) for k in cropped]
        ch = max(y1 - y0 for y0, y1, _, _ in spans)
        cw = max(x1 - x0 for _, _, x0, x1 in spans)
        if ch * cw > WHOLE_IMAGE_SHARE * h * w:  # their common window is about the image: one call for all
            whole, cropped = sorted(whole + cropped), []
    if whole == list(range(b)):  # every term whole: no gathers
        return _masked_terms(preds, targets, weights, counts, ssim_weight)
    values: dict[int, Tensor] = {}
    if whole:
        index = torch.tensor(whole, device=preds.device)
        for k, value in zip(whole, _masked_terms(preds[index], targets[index], weights[index], counts[index],
                                                 ssim_weight).unbind(0)):
            values[k] = value
    if cropped:
        # every term's window has the common size: moved towards the image's inside where it would
        # leave it, it still holds the term's grown box (the box is at most ch x cw)
        origins = [(min(y0, h - ch), min(x0, w - cw)) for y0, _, x0, _ in spans]

        def crop(t: Tensor) -> Tensor:
            return torch.stack([t[k, y:y + ch, x:x + cw] for k, (y, x) in zip(cropped, origins)])

        index = torch.tensor(cropped, device=preds.device)
        for k, value in zip(cropped, _masked_terms(crop(preds), crop(targets), crop(weights), counts[index],
                                                   ssim_weight).unbind(0)):
            values[k] = value
    for k in empty:
        values[k] = (preds[k] * 0.0).sum()
    return torch.stack([values[k] for k in range(b)])


def mask_boxes(support: Tensor) -> list[tuple[int, int, int, int] | None]:
    """Per mask of support [B, H, W] bool: (first row, last row, first column, last column) of its
    True pixels, or None when it has none (one transfer of 5B integers)."""
    b, h, w = support.shape
    rows, cols = support.any(dim=2).to(torch.uint8), support.any(dim=1).to(torch.uint8)  # [B, H], [B, W]
    # argmax returns the first maximum: the first True, and on the flipped axis the last one
    table = torch.stack((rows.argmax(dim=1), h - 1 - rows.flip(1).argmax(dim=1), cols.argmax(dim=1),
                         w - 1 - cols.flip(1).argmax(dim=1), rows.amax(dim=1).long()), dim=1).tolist()
    return [tuple(row[:4]) if row[4] else None for row in table]


def _grown(box: tuple[int, int, int, int], h: int, w: int) -> tuple[int, int, int, int]:
    """[y0, y1) x [x0, x1): the box's pixels and CROP_MARGIN around them, clipped to the image."""
    top, bottom, left, right = box
    return (max(0, top - CROP_MARGIN), min(h, bottom + CROP_MARGIN + 1),
            max(0, left - CROP_MARGIN), min(w, right + CROP_MARGIN + 1))


def _masked_terms(preds: Tensor, targets: Tensor, weights: Tensor, counts: Tensor, ssim_weight: float) -> Tensor:
    """[B] losses of non-empty masks: preds, targets [B, h, w, C], weights [B, h, w, 1] (holding all
    of each mask's weight) and counts [B] (each mask's total weight, >= 1)."""
    safe = counts.clamp_min(1.0)
    filled = torch.where(weights > 0, preds, targets)
    channels = preds.shape[-1]
    l1 = (weights * (filled - targets).abs()).sum(dim=(1, 2, 3)) / (safe * channels)
    if ssim_weight == 0:
        return l1
    ssim_values = ssim_map(filled, targets).mean(dim=-1, keepdim=True)
    d_ssim = 1.0 - (weights * ssim_values).sum(dim=(1, 2, 3)) / safe
    return (1.0 - ssim_weight) * l1 + ssim_weight * d_ssim


def photometric_losses_dense(preds: Tensor, targets: Tensor, masks: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """`photometric_losses` on the whole images: its oracle (tests) and the path with the crop off.

    One batched SSIM call for all B terms (the per-call overhead of the separable convolutions
    dominates at training resolutions).
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
