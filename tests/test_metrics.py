"""PSNR, SSIM (against scikit-image and a direct 2-D convolution), LPIPS availability."""
from __future__ import annotations

import sys
import types

import pytest
import torch
import torch.nn.functional as F
from skimage.metrics import structural_similarity

from baselines import metrics
from baselines.metrics import LpipsMetric, lpips_or_reason, psnr, ssim, ssim_map


def smooth_pair(h=32, w=40, c=3, seed=0, dtype=torch.float64):
    """Two related images with structure at several scales, in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(1, c, h // 4, w // 4, generator=g, dtype=dtype)
    base = F.interpolate(base, size=(h, w), mode="bilinear", align_corners=False)[0]
    img = (base + 0.1 * torch.rand(c, h, w, generator=g, dtype=dtype)).clamp(0, 1)
    gt = (0.8 * base + 0.1 + 0.05 * torch.rand(c, h, w, generator=g, dtype=dtype)).clamp(0, 1)
    return img.permute(1, 2, 0).contiguous(), gt.permute(1, 2, 0).contiguous()


# --- PSNR -------------------------------------------------------------------------------------

def test_psnr_of_known_mse():
    gt = torch.full((8, 10, 3), 0.5)
    sign = torch.where(torch.rand(8, 10, 3) > 0.5, 1.0, -1.0)
    img = gt + 0.1 * sign  # squared error 0.01 everywhere -> 20 dB
    assert psnr(img, gt).item() == pytest.approx(20.0, abs=1e-4)
    batch = torch.stack([gt + 0.1 * sign, gt + 0.01 * sign])  # 20 dB and 40 dB
    out = psnr(batch, torch.stack([gt, gt]))
    assert out.shape == (2,) and out.tolist() == pytest.approx([20.0, 40.0], abs=1e-3)
    assert psnr(gt, gt).item() == float("inf")


def test_psnr_mask_uses_only_masked_pixels():
    gt = torch.zeros(6, 6, 3)
    img = gt.clone()
    img[:3] = 0.1  # error 0.01 in the top half
    img[3:] = 0.5  # large error in the bottom half, masked out
    mask = torch.zeros(6, 6, dtype=torch.bool)
    mask[:3] = True
    assert psnr(img, gt, mask).item() == pytest.approx(20.0, abs=1e-4)
    assert psnr(img, gt, mask[..., None].float()).item() == pytest.approx(20.0, abs=1e-4)
    batched = psnr(img[None].repeat(2, 1, 1, 1), gt[None].repeat(2, 1, 1, 1), mask[None].repeat(2, 1, 1))
    assert batched.tolist() == pytest.approx([20.0, 20.0], abs=1e-4)
    with pytest.raises(ValueError, match="selects no pixel"):
        psnr(img, gt, torch.zeros(6, 6, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask"):
        psnr(img, gt, torch.ones(5, 6))


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="differ in shape"):
        psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match=r"\[H, W, C\]"):
        ssim(torch.zeros(4, 3), torch.zeros(4, 3))
    with pytest.raises(TypeError, match="float"):
        ssim(torch.zeros(4, 4, 3, dtype=torch.uint8), torch.zeros(4, 4, 3, dtype=torch.uint8))


# --- SSIM -------------------------------------------------------------------------------------

def test_ssim_interior_matches_skimage():
    img, gt = smooth_pair()
    ref = structural_similarity(img.numpy(), gt.numpy(), gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False, data_range=1.0, channel_axis=-1)
    # skimage averages the map without a (win - 1) / 2 = 5 pixel border; inside that band both
    # use the same 11-tap window and agree to float64 round-off. On the band they differ by
    # design: 3DGS zero-pads (its local means see zeros), skimage reflects.
    ours = ssim_map(img, gt)[5:-5, 5:-5].mean().item()
    assert ours == pytest.approx(ref, abs=1e-10)
    assert 0.3 < ref < 0.99  # a meaningful (not saturated) test case
    # float32 inputs: same value up to single-precision round-off
    ours32 = ssim_map(img.float(), gt.float())[5:-5, 5:-5].mean().item()
    assert ours32 == pytest.approx(ref, abs=1e-5)


def test_ssim_map_matches_3dgs_2d_convolution_including_borders():
    img, gt = smooth_pair(h=20, w=17, c=3, seed=1)
    x, y = img.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    t = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-t ** 2 / (2 * 1.5 ** 2))
    g = g / g.sum()
    win = (g[:, None] @ g[None, :]).expand(3, 1, 11, 11)

    def filt(z):
        return F.conv2d(z, win, padding=5, groups=3)

    mu1, mu2 = filt(x), filt(y)
    s1, s2, s12 = filt(x * x) - mu1 ** 2, filt(y * y) - mu2 ** 2, filt(x * y) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ref = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s1 + s2 + c2))
    ours = ssim_map(img, gt)
    torch.testing.assert_close(ours, ref[0].permute(1, 2, 0), rtol=0, atol=1e-12)
    assert ssim(img, gt).item() == pytest.approx(ref.mean().item(), abs=1e-12)


def test_ssim_identity_batch_and_gradient():
    img, gt = smooth_pair(h=16, w=16, dtype=torch.float32)
    assert ssim(gt, gt).item() == pytest.approx(1.0, abs=1e-6)
    batch = ssim(torch.stack([img, gt]), torch.stack([gt, gt]))
    assert batch.shape == (2,) and batch[0] < 0.99 and batch[1] == pytest.approx(1.0, abs=1e-6)
    x = img.clone().requires_grad_(True)
    (1.0 - ssim(x, gt)).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_ssim_gradcheck():
    # small on purpose: finite differences cost two SSIM evaluations per input element
    img, gt = smooth_pair(h=8, w=9, c=1, seed=2)
    x = img.clone().requires_grad_(True)
    y = gt.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(ssim, (x, y), eps=1e-6, atol=1e-6)


def test_ssim_gradcheck_with_a_constant_target():
    """The training case (the target needs no gradient) takes its own path: gradcheck it too, and
    its value and gradient equal the path that differentiates both images."""
    img, gt = smooth_pair(h=8, w=9, c=2, seed=3)
    x = img.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: ssim(a, gt), (x,), eps=1e-6, atol=1e-6)
    value = ssim(x, gt)
    (grad,) = torch.autograd.grad(value, x)
    both = ssim(x, gt.clone().requires_grad_(True))
    (grad_both,) = torch.autograd.grad(both, x)
    torch.testing.assert_close(value, both, rtol=0, atol=1e-14)
    torch.testing.assert_close(grad, grad_both, rtol=0, atol=1e-14)

# --- LPIPS ------------------------------------------------------------------------------------

def test_lpips_unavailable_without_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "lpips", None)  # makes `import lpips` raise ImportError
    monkeypatch.setattr(metrics, "_LPIPS", {})
    img, gt = smooth_pair(h=8, w=8, dtype=torch.float32)
    value, reason = lpips_or_reason(img, gt)
    assert value is None and "lpips package is not installed" in reason


def test_lpips_reports_why_on_this_machine(monkeypatch):
    # the real path here (torchvision cannot be installed on a CPU build of torch)
    try:
        import lpips  # noqa: F401
    except Exception:
        pass
    else:
        pytest.skip("lpips is installed here")
    monkeypatch.setattr(metrics, "_LPIPS", {})
    img, gt = smooth_pair(h=8, w=8, dtype=torch.float32)
    value, reason = lpips_or_reason(img, gt, net="alex")
    assert value is None and reason


class _FakeLPIPS(torch.nn.Module):
    """Stands in for lpips.LPIPS: mean absolute difference of the [-1, 1] inputs."""

    built: list[dict] = []

    def __init__(self, **kwargs):
        super().__init__()
        _FakeLPIPS.built.append(kwargs)
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, a, b, normalize=False):
        assert a.ndim == 4 and a.shape[1] == 3 and normalize
        a, b = 2 * a - 1, 2 * b - 1
        return (self.scale * (a - b).abs().mean(dim=(1, 2, 3))).view(-1, 1, 1, 1)


def test_lpips_plumbing_with_fake_module(monkeypatch):
    fake = types.ModuleType("lpips")
    fake.LPIPS = _FakeLPIPS
    monkeypatch.setitem(sys.modules, "lpips", fake)
    _FakeLPIPS.built.clear()
    metric = LpipsMetric("vgg")
    img, gt = smooth_pair(h=8, w=9, dtype=torch.float32)
    value, reason = metric(img, gt)
    assert reason is None and value.shape == ()
    assert value.item() == pytest.approx(2 * (img - gt).abs().mean().item(), rel=1e-5)
    batch, _ = metric(torch.stack([img, gt]), torch.stack([gt, gt]))
    assert batch.shape == (2,) and batch[1].item() == 0.0
    assert _FakeLPIPS.built == [{"net": "vgg", "verbose": False}]  # built once, reused


def test_lpips_missing_weights_reported_once(monkeypatch):
    calls = []

    def failing(**kwargs):
        calls.append(kwargs)
        raise RuntimeError("vgg16 weights not found and downloading is impossible")

    fake = types.ModuleType("lpips")
    fake.LPIPS = failing
    monkeypatch.setitem(sys.modules, "lpips", fake)
    metric = LpipsMetric("vgg")
    img, gt = smooth_pair(h=8, w=8, dtype=torch.float32)
    for _ in range(2):
        value, reason = metric(img, gt)
        assert value is None and "weights not found" in reason and "'vgg'" in reason
    assert len(calls) == 1
    with pytest.raises(ValueError, match="net"):
        LpipsMetric("resnet")
