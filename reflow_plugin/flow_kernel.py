"""Compiled CPU flow channels: the C++ kernel of csrc/flow_kernel.cpp behind a torch autograd Function.

    flow_features_kernel(proj_a, proj_b, near) -> [N, 7]   (as flow.flow_features_torch)

Why compiled: the torch version is about 50 element-wise ops on [N] tensors (validity masks, two
trace-scaled 2x2 square roots, the 2x2 product and c = m_b - A m_a), each with its backward, for
each view of a ReFlow step; the kernel does one pass forward and one backward (hand-written: the
gradients of view a's means2d and conics and view b's means2d and cov2d). flow_features_torch
stays the oracle of the tests and the fallback.

Building and caching as every compiled kernel of the project (baselines/native_build.py).
Switches: `REFLOW4DGS_FLOW_KERNEL=0` (or false/off/no) keeps the torch version;
`REFLOW4DGS_CPU_KERNEL=0` switches off every compiled CPU kernel, this one included. Without a
compiler or when the build fails, the torch version runs and the reason is logged once. Runs for
float32 / float64 CPU tensors of one dtype; everything else takes the torch version.
"""
from __future__ import annotations

import ctypes
import logging
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from baselines import native_build
from baselines.render import Projection

logger = logging.getLogger(__name__)

ENV_SWITCH = "REFLOW4DGS_FLOW_KERNEL"
ENV_ALL_KERNELS = "REFLOW4DGS_CPU_KERNEL"
SOURCE = Path(__file__).resolve().parent / "csrc" / "flow_kernel.cpp"
ABI_VERSION = 1  # must equal kAbiVersion in the C++ source
_SUPPORTED_DTYPES = {torch.float32: "f32", torch.float64: "f64"}


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64, f64 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
    common = [ptr] * 7 + [i64, f64, f64, f64, i64]
    for suffix in _SUPPORTED_DTYPES.values():
        forward = getattr(lib, f"ff_forward_{suffix}")
        forward.argtypes = common + [ptr]
        forward.restype = ctypes.c_int
        backward = getattr(lib, f"ff_backward_{suffix}")
        backward.argtypes = common + [ptr] * 5
        backward.restype = ctypes.c_int
    native_build.check_abi_version(lib, "ff_abi_version", ABI_VERSION, "flow kernel")
    return lib


LIBRARY = native_build.NativeLibrary("flow_kernel", SOURCE, ABI_VERSION, _bind)


def disabled_by_env() -> str | None:
    """The reason the flow kernel is switched off by the environment, or None."""
    return native_build.switched_off_by_env("the compiled flow channels", ENV_SWITCH, ENV_ALL_KERNELS)


def _inputs(proj_a: Projection, proj_b: Projection) -> list[Tensor]:
    return [proj_a.means2d, proj_a.cov2d, proj_a.conics, proj_a.depths, proj_b.means2d, proj_b.cov2d, proj_b.depths]


def unusable_reason(proj_a: Projection, proj_b: Projection) -> str | None:
    """None when the kernel can compute the flow channels of this pair of projections, else why not."""
    reason = disabled_by_env()
    if reason is not None:
        return reason
    tensors = _inputs(proj_a, proj_b)
    if any(t.device.type != "cpu" for t in tensors):
        return "the compiled flow channels need CPU tensors"
    dtypes = {t.dtype for t in tensors}
    if len(dtypes) != 1 or next(iter(dtypes)) not in _SUPPORTED_DTYPES:
        return f"the compiled flow channels need float32 or float64 projections of one dtype, got {sorted(map(str, dtypes))}"
    ok, reason = LIBRARY.available()
    return None if ok else reason


_logged_reasons: set[str] = set()


def log_fallback_once(reason: str) -> None:
    """Log (once per distinct reason and process) that the flow channels take the torch version."""
    if reason in _logged_reasons:
        return
    _logged_reasons.add(reason)
    quiet = reason == disabled_by_env() or "CPU tensors" in reason or "dtype" in reason
    logger.log(logging.INFO if quiet else logging.WARNING, "flow channels: using the torch version because %s", reason)


def _check(status: int, stage: str) -> None:
    if status == 2:
        raise MemoryError(f"the compiled flow channels ran out of memory in their {stage} pass")
    if status != 0:
        raise RuntimeError(f"the compiled flow channels failed in their {stage} pass (status {status})")


class _FlowKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, ma, cov_a, conic_a, depth_a, mb, cov_b, depth_b, limits: tuple[float, float, float],
                threads: int):
        tensors = [t.detach().contiguous() for t in (ma, cov_a, conic_a, depth_a, mb, cov_b, depth_b)]
        n = tensors[0].shape[0]
        out = torch.empty(n, 7, dtype=ma.dtype)
        status = getattr(LIBRARY.load(), f"ff_forward_{_SUPPORTED_DTYPES[ma.dtype]}")(
            *(t.data_ptr() for t in tensors), n, *limits, threads, out.data_ptr())
        _check(status, "forward")
        ctx.save_for_backward(*tensors)
        ctx.config = (limits, threads)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        tensors = ctx.saved_tensors
        limits, threads = ctx.config
        ma, _cov_a, conic_a, _depth_a, mb, cov_b, _depth_b = tensors
        grad_out = grad_out.to(ma.dtype).contiguous()
        grads = [torch.empty_like(t) for t in (ma, conic_a, mb, cov_b)]
        status = getattr(LIBRARY.load(), f"ff_backward_{_SUPPORTED_DTYPES[ma.dtype]}")(
            *(t.data_ptr() for t in tensors), ma.shape[0], *limits, threads, grad_out.data_ptr(),
            *(g.data_ptr() for g in grads))
        _check(status, "backward")
        g_ma, g_conic_a, g_mb, g_cov_b = grads
        return g_ma, None, g_conic_a, None, g_mb, g_cov_b, None, None, None


def flow_features_kernel(proj_a: Projection, proj_b: Projection, near: float, max_trace: float, max_screen: float,
                         num_threads: int | None = None) -> Tensor:
    """[N, 7] flow channels by the compiled kernel (the caller checks `unusable_reason` first).

    Args:
        proj_a, proj_b: the same N Gaussians projected into views a and b.
        near: near plane; max_trace, max_screen: the plausibility bounds (squared footprint px, px).
    """
    threads = num_threads or torch.get_num_threads()
    return _FlowKernel.apply(*_inputs(proj_a, proj_b), (float(near), float(max_trace), float(max_screen)),
                             int(threads))
