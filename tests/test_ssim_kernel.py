"""Compiled SSIM map (baselines/ssim_kernel.py) against ssim_map_torch, its torch twin.

The twin is the oracle (test_metrics.py checks it against 3DGS's 2-D convolution and
scikit-image; those tests now run through the kernel too, ssim_map dispatching to it).
Covered: values and the image gradient (float32, float64) for batches of 1 and many, C = 1 and 3,
images smaller than the window; gradcheck in float64; the zero-padded border against a closed
form; identical and constant images; the masked photometric terms of ReFlow's flow matching;
thread-count independence; the dispatch rules and the fallbacks (switches, gt needing a gradient,
mixed dtypes, no compiler).
"""
from __future__ import annotations

import logging

import pytest
import torch

from baselines import native_build, ssim_kernel
from baselines.metrics import SSIM_C1, SSIM_C2, gaussian_window_1d, ssim, ssim_map, ssim_map_torch
from reflow_plugin.warp import photometric_losses

KERNEL_GRAD = "_SsimKernelBackward"
TOL = {torch.float32: {"rtol": 1e-5, "atol": 1e-5}, torch.float64: {"rtol": 1e-12, "atol": 1e-12}}


@pytest.fixture(scope="module")
def compiled():
    ok, reason = ssim_kernel.LIBRARY.available()
    if not ok and native_build.find_compiler() is None:
        pytest.skip(reason)
    assert ok, reason  # a compiler is present: the kernel must build
    return ok


def _images(shape, dtype, seed=0):
    """A smooth-plus-noise image and a perturbed target in [0, 1] (local variances of all sizes)."""
    g = torch.Generator().manual_seed(seed)
    b, h, w, c = shape
    ramp = torch.linspace(0, 1, h * w, dtype=dtype).view(1, h, w, 1)
    gt = (0.6 * ramp + 0.4 * torch.rand(shape, generator=g, dtype=dtype)).clamp(0, 1)
    img = (gt + 0.2 * torch.randn(shape, generator=g, dtype=dtype)).clamp(0, 1)
    return img, gt


def _map_and_grad(fn, img, gt, seed=0):
    x = img.detach().clone().requires_grad_()
    out = fn(x, gt)
    weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=out.dtype)
    (grad,) = torch.autograd.grad((out * weights).sum(), x)
    return out, grad, out.grad_fn


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 23, 31, 3), (5, 17, 12, 1), (2, 4, 5, 3), (1, 3, 40, 1)],
                         ids=["one_rgb", "many_gray", "below_window", "three_rows"])
def test_kernel_equals_torch_twin(compiled, dtype, shape):
    img, gt = _images(shape, dtype)
    want, want_grad, _ = _map_and_grad(ssim_map_torch, img, gt)
    got, got_grad, grad_fn = _map_and_grad(ssim_map, img, gt)
    assert type(grad_fn).__name__ == KERNEL_GRAD
    torch.testing.assert_close(got, want, **TOL[dtype])
    scale = want_grad.abs().max()
    torch.testing.assert_close(got_grad / scale, want_grad / scale, **TOL[dtype])


def test_unbatched_image_and_no_grad_call(compiled):
    img, gt = _images((1, 14, 19, 3), torch.float64, seed=1)
    want = ssim_map_torch(img[0], gt[0])
    got = ssim_map(img[0].requires_grad_(), gt[0])
    assert got.shape == (14, 19, 3) and type(got.grad_fn.next_functions[0][0]).__name__ == KERNEL_GRAD
    torch.testing.assert_close(got, want, **TOL[torch.float64])
    with torch.no_grad():  # no partials stored, the same map
        plain = ssim_map(img, gt)
    assert plain.grad_fn is None
    assert torch.equal(plain[0], got.detach())


def test_kernel_passes_gradcheck(compiled):
    img, gt = _images((2, 9, 13, 2), torch.float64, seed=2)
    x = img.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a: ssim_map(a, gt), (x,), eps=1e-6, atol=1e-7, rtol=1e-5)
    assert torch.autograd.gradcheck(lambda a: ssim(a, gt), (x,), eps=1e-6, atol=1e-8, rtol=1e-5)


def test_zero_padded_border_matches_the_closed_form(compiled):
    # Constant images a and b: under a window covering the image with weight s (s = 1 inside,
    # less within 5 pixels of the border, where the zero padding takes the rest), mu = s a,
    # E[x^2] = s a^2, so sigma_x^2 = s (1 - s) a^2 and sigma_xy = s (1 - s) a b.
    h, w, a, b = 16, 13, 0.3, 0.8
    taps = gaussian_window_1d(dtype=torch.float64)
    cover = lambda n: torch.stack([taps[max(0, 5 - i):min(11, n + 5 - i)].sum() for i in range(n)])  # noqa: E731
    s = cover(h)[:, None] * cover(w)[None, :]  # [H, W]
    v = s * (1 - s)
    want = ((2 * s * s * a * b + SSIM_C1) * (2 * v * a * b + SSIM_C2)
            / ((s * s * (a * a + b * b) + SSIM_C1) * (v * (a * a + b * b) + SSIM_C2)))
    img = torch.full((1, h, w, 1), a, dtype=torch.float64, requires_grad=True)
    got = ssim_map(img, torch.full((1, h, w, 1), b, dtype=torch.float64))
    assert type(got.grad_fn).__name__ == KERNEL_GRAD
    torch.testing.assert_close(got[0, ..., 0], want, rtol=1e-12, atol=1e-13)
    assert got[0, 0, 0, 0] < got[0, 8, 6, 0]  # the border differs from the interior


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_identical_images_give_one_and_a_zero_gradient(compiled, dtype):
    img, _ = _images((2, 12, 15, 3), dtype, seed=3)
    flat = torch.full((1, 12, 15, 3), 0.4, dtype=dtype)
    for x in (img, flat):  # SSIM <= 1 with equality at x = y: a maximum, so the gradient vanishes
        out, grad, grad_fn = _map_and_grad(ssim_map, x, x.clone())
        assert type(grad_fn).__name__ == KERNEL_GRAD
        torch.testing.assert_close(out, torch.ones_like(out), rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)
        assert grad.abs().max() < (1e-5 if dtype == torch.float32 else 1e-10)


def test_masked_photometric_terms_equal_the_torch_twin(compiled, monkeypatch):
    g = torch.Generator().manual_seed(4)
    preds, targets = _images((4, 20, 24, 3), torch.float32, seed=4)
    masks = torch.rand(4, 20, 24, generator=g) > 0.4
    masks[3] = False  # an empty mask: a zero still connected to the graph

    def losses_and_grad():
        x = preds.detach().clone().requires_grad_()
        loss = photometric_losses(x, targets, masks, ssim_weight=0.2)
        (grad,) = torch.autograd.grad(loss.sum(), x)
        return loss, grad

    got, got_grad = losses_and_grad()
    monkeypatch.setenv(ssim_kernel.ENV_SWITCH, "0")
    want, want_grad = losses_and_grad()
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got_grad, want_grad, rtol=1e-4, atol=1e-8)
    assert got[3] == 0 and got_grad.abs().sum() > 0


def test_results_do_not_depend_on_the_thread_count(compiled):
    taps = gaussian_window_1d(dtype=torch.float32)
    for shape in ((1, 90, 21, 3), (2, 40, 9, 1)):  # one image in row blocks; two images over three threads
        img, gt = _images(shape, torch.float32, seed=5)
        results = []
        for threads in (1, 3, 4):
            x = img.detach().clone().requires_grad_()
            out = ssim_kernel.ssim_map_kernel(x, gt, taps, SSIM_C1, SSIM_C2, num_threads=threads)
            (grad,) = torch.autograd.grad(out.sum(), x)
            results.append((out, grad))
        for out, grad in results[1:]:
            assert torch.equal(out, results[0][0]) and torch.equal(grad, results[0][1])


def test_dispatch_and_fallbacks(compiled, monkeypatch, caplog):
    img, gt = _images((1, 10, 12, 3), torch.float32, seed=6)
    x = img.requires_grad_()
    monkeypatch.setattr(ssim_kernel, "_logged_reasons", set())
    with caplog.at_level(logging.INFO, logger=ssim_kernel.__name__):
        for name in (ssim_kernel.ENV_SWITCH, ssim_kernel.ENV_ALL_KERNELS):
            monkeypatch.setenv(name, "off")
            assert type(ssim_map(x, gt).grad_fn).__name__ != KERNEL_GRAD
            assert type(ssim_map(x, gt).grad_fn).__name__ != KERNEL_GRAD  # logged once per reason
            monkeypatch.delenv(name)
    assert len([r for r in caplog.records if r.name == ssim_kernel.__name__]) == 2
    # a target that needs a gradient: the torch twin differentiates both images
    y = gt.clone().requires_grad_()
    out = ssim_map(x, y)
    assert type(out.grad_fn).__name__ != KERNEL_GRAD
    grad_x, grad_y = torch.autograd.grad(out.sum(), (x, y))
    assert grad_y.abs().sum() > 0
    torch.testing.assert_close(grad_x, torch.autograd.grad(ssim_map_torch(x, y).sum(), x)[0])
    # mixed dtypes and half precision take the torch twin
    assert ssim_kernel.unusable_reason(img, gt.double()) is not None
    assert ssim_kernel.unusable_reason(img.half(), gt.half()) is not None
    with pytest.raises(ValueError, match="11 taps"):
        ssim_kernel.ssim_map_kernel(img, gt, torch.ones(7), SSIM_C1, SSIM_C2)


def test_missing_compiler_falls_back_to_the_torch_twin(monkeypatch, tmp_path, caplog):
    monkeypatch.setenv(native_build.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.setenv("CXX", "no-such-compiler-reflow4dgs")
    monkeypatch.setattr(ssim_kernel, "_logged_reasons", set())
    ssim_kernel.LIBRARY.reset()
    try:
        img, gt = _images((2, 11, 9, 3), torch.float32, seed=7)
        with caplog.at_level(logging.INFO, logger=ssim_kernel.__name__):
            got = ssim_map(img, gt)
        assert torch.equal(got, ssim_map_torch(img, gt))
        records = [r for r in caplog.records if r.name == ssim_kernel.__name__]
        assert len(records) == 1 and records[0].levelno == logging.WARNING
        assert "no C++ compiler" in records[0].getMessage()
    finally:
        ssim_kernel.LIBRARY.reset()
