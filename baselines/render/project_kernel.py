"""Compiled CPU projection: the C++ kernel of csrc/project_kernel.cpp behind a torch autograd Function.

    project_gaussians_kernel(means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d)
        -> Projection   (same arguments, outputs and rules as projection.project_gaussians_torch)

Why compiled: the torch projection is a graph of about 60 element-wise ops on [N] tensors per
view, and its backward a few more per op; at real-capture scale (30k Gaussians, four projections
per ReFlow step) their dispatch and temporaries were a large share of a CPU iteration. The kernel
does one pass over the Gaussians forward and one backward (hand-written: the gradients of means,
quats and scales from those of means2d, cov2d, conics and depths). project_gaussians_torch stays
the oracle of the tests (values and gradients) and the fallback.

Building and caching as every compiled kernel here (baselines/native_build.py). Switches:
`REFLOW4DGS_PROJECT_KERNEL=0` (or false/off/no) keeps the torch projection;
`REFLOW4DGS_CPU_KERNEL=0` switches off every compiled CPU kernel, this one included. Without a
compiler or when the build fails, the torch path runs and the reason is logged once. The kernel
runs for float32 / float64 CPU tensors whose camera (viewmat, K) needs no gradient; everything
else takes the torch path.
"""
from __future__ import annotations

import ctypes
import logging
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from baselines import native_build

from .projection import Projection, project_gaussians_torch

logger = logging.getLogger(__name__)

ENV_SWITCH = "REFLOW4DGS_PROJECT_KERNEL"
ENV_ALL_KERNELS = "REFLOW4DGS_CPU_KERNEL"
SOURCE = Path(__file__).resolve().parent / "csrc" / "project_kernel.cpp"
ABI_VERSION = 1  # must equal kAbiVersion in the C++ source
_SUPPORTED_DTYPES = {torch.float32: "f32", torch.float64: "f64"}


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64, f64 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
    camera = [i64, i64, i64, f64, f64, f64, i64]  # n, width, height, near, far, eps2d, threads
    for suffix in _SUPPORTED_DTYPES.values():
        forward = getattr(lib, f"pj_forward_{suffix}")
        forward.argtypes = [ptr] * 6 + camera + [ptr] * 6
        forward.restype = ctypes.c_int
        backward = getattr(lib, f"pj_backward_{suffix}")
        backward.argtypes = [ptr] * 5 + camera + [ptr] * 7
        backward.restype = ctypes.c_int
    native_build.check_abi_version(lib, "pj_abi_version", ABI_VERSION, "projection kernel")
    return lib


LIBRARY = native_build.NativeLibrary("project_kernel", SOURCE, ABI_VERSION, _bind)


def disabled_by_env() -> str | None:
    """The reason the projection kernel is switched off by the environment, or None."""
    return native_build.switched_off_by_env("the compiled projection", ENV_SWITCH, ENV_ALL_KERNELS)


def unusable_reason(means: Tensor, viewmat: Tensor, K: Tensor) -> str | None:
    """None when the kernel can project Gaussians like `means` into this camera, else why not."""
    reason = disabled_by_env()
    if reason is not None:
        return reason
    if means.device.type != "cpu":
        return f"the compiled projection needs CPU tensors, got {means.device}"
    if means.dtype not in _SUPPORTED_DTYPES:
        return f"the compiled projection supports float32 and float64, got {means.dtype}"
    if viewmat.requires_grad or K.requires_grad:
        return "the compiled projection does not differentiate the camera (viewmat or K requires grad)"
    ok, reason = LIBRARY.available()
    return None if ok else reason


_logged_reasons: set[str] = set()


def log_fallback_once(reason: str) -> None:
    """Log (once per distinct reason and process) that the projection takes the torch path."""
    if reason in _logged_reasons:
        return
    _logged_reasons.add(reason)
    quiet = reason == disabled_by_env() or "CPU tensors" in reason or "supports float32" in reason or "camera" in reason
    logger.log(logging.INFO if quiet else logging.WARNING, "projection: using the torch path because %s", reason)


def _check(status: int, stage: str) -> None:
    if status == 2:
        raise MemoryError(f"the compiled projection ran out of memory in its {stage} pass")
    if status != 0:
        raise RuntimeError(f"the compiled projection failed in its {stage} pass (status {status})")


def _ptr(t: Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


class _ProjectKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width: int, height: int, near: float,
                far: float, eps2d: float, threads: int):
        lib = LIBRARY.load()
        dtype = means.dtype
        means, quats, scales = (x.detach().contiguous() for x in (means, quats, scales))
        viewmat, K = viewmat.detach().to(dtype).contiguous(), K.detach().to(dtype).contiguous()
        opac = None if opacities is None else opacities.detach().to(dtype).contiguous()
        n = means.shape[0]
        means2d = torch.empty(n, 2, dtype=dtype)
        cov2d = torch.empty(n, 2, 2, dtype=dtype)
        conics = torch.empty(n, 3, dtype=dtype)
        depths = torch.empty(n, dtype=dtype)
        radii = torch.empty(n, 2, dtype=torch.int32)
        visible = torch.empty(n, dtype=torch.bool)
        status = getattr(lib, f"pj_forward_{_SUPPORTED_DTYPES[dtype]}")(
            means.data_ptr(), quats.data_ptr(), scales.data_ptr(), _ptr(opac), viewmat.data_ptr(), K.data_ptr(),
            n, width, height, near, far, eps2d, threads, means2d.data_ptr(), cov2d.data_ptr(), conics.data_ptr(),
            depths.data_ptr(), radii.data_ptr(), visible.data_ptr())
        _check(status, "forward")
        ctx.save_for_backward(means, quats, scales, viewmat, K)
        ctx.config = (width, height, near, far, eps2d, threads)
        ctx.mark_non_differentiable(radii, visible)
        return means2d, cov2d, conics, depths, radii, visible

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_cov2d, g_conics, g_depths, _g_radii, _g_visible):
        means, quats, scales, viewmat, K = ctx.saved_tensors
        width, height, near, far, eps2d, threads = ctx.config
        dtype = means.dtype
        grads = [None if g is None else g.to(dtype).contiguous() for g in (g_means2d, g_cov2d, g_conics, g_depths)]
        g_means, g_quats, g_scales = torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales)
        status = getattr(LIBRARY.load(), f"pj_backward_{_SUPPORTED_DTYPES[dtype]}")(
            means.data_ptr(), quats.data_ptr(), scales.data_ptr(), viewmat.data_ptr(), K.data_ptr(),
            means.shape[0], width, height, near, far, eps2d, threads, *(_ptr(g) for g in grads),
            g_means.data_ptr(), g_quats.data_ptr(), g_scales.data_ptr())
        _check(status, "backward")
        return g_means, g_quats, g_scales, None, None, None, None, None, None, None, None, None


def project_gaussians_kernel(
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
    num_threads: int | None = None,
) -> Projection:
    """The compiled projection (arguments and outputs as project_gaussians_torch).

    The caller checks `unusable_reason` first (`project_gaussians_cpu` does). Quats and scales
    are cast to the means' dtype, as the torch twin's type promotion would.
    """
    dtype = means.dtype
    threads = num_threads or torch.get_num_threads()
    means2d, cov2d, conics, depths, radii, visible = _ProjectKernel.apply(
        means, quats.to(dtype), scales.to(dtype), opacities, viewmat, K, int(width), int(height), float(near),
        float(far), float(eps2d), int(threads))
    return Projection(means2d=means2d, cov2d=cov2d, conics=conics, depths=depths, radii=radii, visible=visible)


def project_gaussians_cpu(means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor, K: Tensor, width: int,
                          height: int, opacities: Tensor | None = None, near: float = 0.01, far: float = 1e10,
                          eps2d: float = 0.3) -> Projection:
    """The cpu backend's projection: the compiled kernel where it can run, else the torch twin."""
    reason = unusable_reason(means, viewmat, K)
    if reason is None:
        return project_gaussians_kernel(means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d)
    log_fallback_once(reason)
    return project_gaussians_torch(means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d)
