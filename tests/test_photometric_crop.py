"""ReFlow's masked photometric terms on their masks' boxes (reflow_plugin/warp.py) against the
whole-image evaluation, `photometric_losses_dense`, the oracle.

A mask pixel's SSIM reads the pixels within CROP_MARGIN of it; the crop must keep them all (or the
zero padding where the box meets the image edge). The masks here put boxes in the interior (a
margin one pixel short changes the SSIM of the box's edge pixels), at the four edges, of several
sizes in one batch (the common window moved inside the image), plus a mask spread over the image
(the whole-image group), empty and sub-unit-weight masks (the connected zero) and float weights.
"""
from __future__ import annotations

import pytest
import torch

from baselines import ssim_kernel
from reflow_plugin import warp
from reflow_plugin.warp import mask_boxes, photometric_losses, photometric_losses_dense

H, W = 40, 52


def _batch(dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """preds, targets [B, H, W, 3] in [0, 1] and float masks [B, H, W] of every kind named above."""
    g = torch.Generator().manual_seed(seed)
    targets = torch.rand(8, H, W, 3, generator=g, dtype=dtype)
    preds = (targets + 0.2 * torch.randn(8, H, W, 3, generator=g, dtype=dtype)).clamp(0, 1)
    masks = torch.zeros(8, H, W, dtype=dtype)
    masks[0, 12:20, 15:30] = 1.0  # interior
    masks[1, 20:27, 8:14] = 1.0  # interior, another size and place
    masks[1, 22, 20] = 1.0  # a lone pixel apart from the rest
    masks[2, 0:6, 0:9] = 1.0  # top-left corner
    masks[3, 33:40, 44:52] = torch.rand(7, 8, generator=g, dtype=dtype) * 0.9 + 0.1  # bottom-right, float weights
    masks[4] = (torch.rand(H, W, generator=g, dtype=dtype) > 0.5).to(dtype)  # spread: the whole-image group
    # masks[5] stays empty
    masks[6, 10, 10] = 0.5  # a weight below one pixel's: the connected zero
    masks[7, 10:22, 0:4] = 1.0  # left edge
    return preds, targets, masks


def _losses_and_grad(fn, preds, targets, masks):
    x = preds.detach().clone().requires_grad_()
    loss = fn(x, targets, masks, ssim_weight=0.2)
    (grad,) = torch.autograd.grad((loss * torch.arange(1, 9, dtype=loss.dtype)).sum(), x)
    return loss, grad


@pytest.mark.parametrize("ssim_path", ["kernel", "torch"])
def test_cropped_terms_equal_the_whole_image_in_float64(ssim_path, monkeypatch):
    if ssim_path == "torch":
        monkeypatch.setenv(ssim_kernel.ENV_SWITCH, "0")
    preds, targets, masks = _batch(torch.float64)
    seen = []
    real = warp.ssim_map
    monkeypatch.setattr(warp, "ssim_map", lambda x, y: seen.append(tuple(x.shape)) or real(x, y))
    got, got_grad = _losses_and_grad(photometric_losses, preds, targets, masks)
    calls = list(seen)  # the oracle's call below is not the crop's
    want, want_grad = _losses_and_grad(photometric_losses_dense, preds, targets, masks)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(got_grad, want_grad, rtol=1e-12, atol=1e-14)
    # the small boxes went through one SSIM call on a window smaller than the image, the spread
    # mask through one on the whole image; the empty and sub-unit masks through none
    assert len(calls) == 2 and calls[0] == (1, H, W, 3)
    assert calls[1][0] == 5 and calls[1][1] * calls[1][2] < 0.3 * H * W
    assert got[5] == 0 and got[6] == 0 and bool((got[[0, 1, 2, 3, 4, 7]] > 0).all())


def test_cropped_terms_equal_the_whole_image_in_float32():
    preds, targets, masks = _batch(torch.float32, seed=1)
    got, got_grad = _losses_and_grad(photometric_losses, preds, targets, masks)
    want, want_grad = _losses_and_grad(photometric_losses_dense, preds, targets, masks)
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(got_grad, want_grad, rtol=1e-5, atol=1e-9)


def test_a_window_most_of_the_image_takes_one_whole_image_call(monkeypatch):
    preds, targets, _ = _batch(torch.float64, seed=2)
    masks = torch.zeros(2, H, W, dtype=torch.float64)
    masks[0, 0:34, 0:10] = 1.0  # tall and narrow, a third of the image with its margin
    masks[1, 0:10, 0:40] = 1.0  # short and wide, likewise: together they need most of the image
    seen = []
    real = warp.ssim_map
    monkeypatch.setattr(warp, "ssim_map", lambda x, y: seen.append(tuple(x.shape)) or real(x, y))
    x = preds[:2].detach().clone().requires_grad_()
    got = photometric_losses(x, targets[:2], masks)
    want = photometric_losses_dense(x, targets[:2], masks)
    assert seen[0] == (2, H, W, 3)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)


def test_the_switch_restores_the_whole_image_path(monkeypatch):
    preds, targets, masks = _batch(torch.float64, seed=3)
    seen = []
    real = warp.ssim_map
    monkeypatch.setattr(warp, "ssim_map", lambda x, y: seen.append(tuple(x.shape)) or real(x, y))
    monkeypatch.setenv(warp.CROP_SWITCH, "0")
    photometric_losses(preds, targets, masks)
    assert seen == [(8, H, W, 3)]


def test_mask_boxes_are_the_first_and_last_rows_and_columns():
    support = torch.zeros(3, 6, 7, dtype=torch.bool)
    support[0, 2, 3] = True
    support[1, 0:2, 4] = True
    support[1, 5, 6] = True
    assert mask_boxes(support) == [(2, 2, 3, 3), (0, 5, 4, 6), None]
