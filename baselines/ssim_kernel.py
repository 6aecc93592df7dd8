"""Compiled CPU SSIM map: the C++ kernel of csrc/ssim_kernel.cpp behind a torch autograd Function.

    ssim_map_kernel(img, gt) -> [B, H, W, C]   (img, gt: [B, H, W, C]; as metrics.ssim_map_torch)

Why compiled: the torch version permutes the channels-last images, concatenates five planes,
runs two grouped convolutions and about fifteen element-wise ops, each with its backward; a
ReFlow step evaluates it on [8, H, W, 3] (flow matching's masked photometric terms) and [2, H, W, 3]
(the host's D-SSIM), about a quarter of a one-thread CPU step at 320x180. The kernel filters the
five moments of each row in place (channels-last, no permutes) and forms the map in one pass;
when img needs a gradient the forward also stores three per-pixel partials, so the backward
(hand-written, derivation in the C++ source) is one three-plane separable filtering. The
gradient flows to img only: a gt that requires grad takes the torch version (metrics.ssim_map
decides). metrics.ssim_map_torch stays the oracle of the tests and the fallback.

Building and caching as every compiled kernel of the project (baselines/native_build.py).
Switches: `REFLOW4DGS_SSIM_KERNEL=0` (or false/off/no) keeps the torch version;
`REFLOW4DGS_CPU_KERNEL=0` switches off every compiled CPU kernel, this one included. Without a
compiler or when the build fails, the torch version runs and the reason is logged once. Runs for
float32 / float64 CPU images of one dtype; everything else takes the torch version.
"""
from __future__ import annotations

import ctypes
import logging
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from baselines import native_build

logger = logging.getLogger(__name__)

ENV_SWITCH = "REFLOW4DGS_SSIM_KERNEL"
ENV_ALL_KERNELS = "REFLOW4DGS_CPU_KERNEL"
SOURCE = Path(__file__).resolve().parent / "csrc" / "ssim_kernel.cpp"
ABI_VERSION = 1  # must equal kAbiVersion in the C++ source
WINDOW = 11  # must equal kTaps in the C++ source
_SUPPORTED_DTYPES = {torch.float32: "f32", torch.float64: "f64"}


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64, f64 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
    shape = [i64] * 4  # b, h, w, c
    for suffix in _SUPPORTED_DTYPES.values():
        forward = getattr(lib, f"ssim_forward_{suffix}")
        forward.argtypes = [ptr] * 3 + shape + [f64, f64, i64] + [ptr] * 4
        forward.restype = ctypes.c_int
        backward = getattr(lib, f"ssim_backward_{suffix}")
        backward.argtypes = [ptr] * 3 + shape + [i64] + [ptr] * 5
        backward.restype = ctypes.c_int
    native_build.check_abi_version(lib, "ssim_abi_version", ABI_VERSION, "SSIM kernel")
    return lib


LIBRARY = native_build.NativeLibrary("ssim_kernel", SOURCE, ABI_VERSION, _bind)


def disabled_by_env() -> str | None:
    """The reason the SSIM kernel is switched off by the environment, or None."""
    return native_build.switched_off_by_env("the compiled SSIM", ENV_SWITCH, ENV_ALL_KERNELS)


def unusable_reason(img: Tensor, gt: Tensor) -> str | None:
    """None when the kernel can compute the SSIM map of these [B, H, W, C] images, else why not."""
    reason = disabled_by_env()
    if reason is not None:
        return reason
    if img.device.type != "cpu" or gt.device.type != "cpu":
        return "the compiled SSIM needs CPU tensors"
    if img.dtype != gt.dtype or img.dtype not in _SUPPORTED_DTYPES:
        return f"the compiled SSIM needs float32 or float64 images of one dtype, got {img.dtype} and {gt.dtype}"
    if gt.requires_grad and torch.is_grad_enabled():
        return "the compiled SSIM does not differentiate the target (gt requires grad)"
    ok, reason = LIBRARY.available()
    return None if ok else reason


_logged_reasons: set[str] = set()


def log_fallback_once(reason: str) -> None:
    """Log (once per distinct reason and process) that the SSIM map takes the torch version."""
    if reason in _logged_reasons:
        return
    _logged_reasons.add(reason)
    quiet = reason == disabled_by_env() or "CPU tensors" in reason or "dtype" in reason or "target" in reason
    logger.log(logging.INFO if quiet else logging.WARNING, "SSIM: using the torch version because %s", reason)


def _check(status: int, stage: str) -> None:
    if status == 2:
        raise MemoryError(f"the compiled SSIM ran out of memory in its {stage} pass")
    if status != 0:
        raise RuntimeError(f"the compiled SSIM failed in its {stage} pass (status {status})")


def _forward(x: Tensor, y: Tensor, taps: Tensor, c1: float, c2: float, threads: int,
             with_partials: bool) -> tuple[Tensor, Tensor | None]:
    """(SSIM map [B, H, W, C], partials [3, B, H, W, C] or None) of contiguous x, y."""
    out = torch.empty_like(x)
    partials = torch.empty((3, *x.shape), dtype=x.dtype) if with_partials else None
    planes = [None] * 3 if partials is None else [p.data_ptr() for p in partials]
    status = getattr(LIBRARY.load(), f"ssim_forward_{_SUPPORTED_DTYPES[x.dtype]}")(
        x.data_ptr(), y.data_ptr(), taps.data_ptr(), *x.shape, c1, c2, threads, out.data_ptr(), *planes)
    _check(status, "forward")
    return out, partials


class _SsimKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, img, gt, taps, constants: tuple[float, float], threads: int):
        x, y = img.detach().contiguous(), gt.detach().contiguous()
        out, partials = _forward(x, y, taps, *constants, threads, with_partials=True)
        ctx.save_for_backward(x, y, taps, partials)
        ctx.threads = threads
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        x, y, taps, partials = ctx.saved_tensors
        grad_out = grad_out.to(x.dtype).contiguous()
        grad_x = torch.empty_like(x)
        status = getattr(LIBRARY.load(), f"ssim_backward_{_SUPPORTED_DTYPES[x.dtype]}")(
            x.data_ptr(), y.data_ptr(), taps.data_ptr(), *x.shape, ctx.threads, grad_out.data_ptr(),
            *(p.data_ptr() for p in partials), grad_x.data_ptr())
        _check(status, "backward")
        return grad_x, None, None, None, None


def ssim_map_kernel(img: Tensor, gt: Tensor, taps: Tensor, c1: float, c2: float,
                    num_threads: int | None = None) -> Tensor:
    """[B, H, W, C] SSIM map by the compiled kernel (the caller checks `unusable_reason` first).

    Args:
        img, gt: [B, H, W, C] images of one float dtype on the CPU; the gradient flows to img only.
        taps: [WINDOW] normalised 1-D Gaussian window in that dtype. c1, c2: SSIM's constants.
    """
    if taps.shape != (WINDOW,):
        raise ValueError(f"ssim_map_kernel: the window must have {WINDOW} taps, got {tuple(taps.shape)}")
    threads = int(num_threads or torch.get_num_threads())
    taps = taps.detach().to(img.dtype).contiguous()
    if torch.is_grad_enabled() and img.requires_grad:
        return _SsimKernel.apply(img, gt, taps, (float(c1), float(c2)), threads)
    out, _ = _forward(img.detach().contiguous(), gt.detach().contiguous(), taps, float(c1), float(c2), threads,
                      with_partials=False)
    return out
