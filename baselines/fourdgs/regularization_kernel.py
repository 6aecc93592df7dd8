"""Compiled CPU HexPlane regularisers: the C++ kernel of csrc/regularization_kernel.cpp behind an autograd Function.

    weighted_plane_regularisation(smooth_weights, l1_weights, planes) -> total (0-dim tensor)

Same value and gradients as regularization._WeightedPlaneRegularisation (the torch Function, which
stays the oracle of the tests and the fallback): sum over planes of smooth x mean squared second
difference along dimension -2 plus l1 x mean |1 - plane|. Why compiled: the torch Function makes
about 15 passes over the planes per step (7.35M values on a DAVIS model, 80-90 ms on one thread);
the kernel reads each plane once and writes its gradient once, in the forward (the smoothness
gradient is linear in the plane, the L1 gradient a sign), and the backward only scales the saved
gradients by the incoming one (nothing at all when it is 1, as in training).

Building and caching as every compiled kernel here (baselines/native_build.py). Switches:
`REFLOW4DGS_REG_KERNEL=0` (or false/off/no) keeps the torch Function; `REFLOW4DGS_CPU_KERNEL=0`
switches off every compiled CPU kernel, this one included. Without a compiler or when the build
fails, the torch Function runs and the reason is logged once. Dtypes: float32 and float64 CPU
planes of one dtype (others take the torch Function). Any strides: each plane's pointer and
strides go to the kernel (views into plane_lookup's shared channels-last table copy nothing).
"""
from __future__ import annotations

import ctypes
import logging
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from baselines import native_build

logger = logging.getLogger(__name__)

ENV_SWITCH = "REFLOW4DGS_REG_KERNEL"
ENV_ALL_KERNELS = "REFLOW4DGS_CPU_KERNEL"
SOURCE = Path(__file__).resolve().parent / "csrc" / "regularization_kernel.cpp"
ABI_VERSION = 1  # must equal kAbiVersion in the C++ source
_SUPPORTED_DTYPES = {torch.float32: "f32", torch.float64: "f64"}


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    for suffix in _SUPPORTED_DTYPES.values():
        forward = getattr(lib, f"rk_forward_{suffix}")
        forward.argtypes = [i64, ptr, ptr, ptr, ptr, ptr, ptr, i64, ptr]
        forward.restype = ctypes.c_int
    native_build.check_abi_version(lib, "rk_abi_version", ABI_VERSION, "regularisation kernel")
    return lib


LIBRARY = native_build.NativeLibrary("regularization_kernel", SOURCE, ABI_VERSION, _bind)


def disabled_by_env() -> str | None:
    """The reason the regularisation kernel is switched off by the environment, or None."""
    return native_build.switched_off_by_env("the compiled regularisation kernel", ENV_SWITCH, ENV_ALL_KERNELS)


def unusable_reason(planes: Sequence[Tensor]) -> str | None:
    """None when the kernel can regularise `planes` (each [B, C, H, W]), else why not."""
    reason = disabled_by_env()
    if reason is not None:
        return reason
    if any(p.device.type != "cpu" for p in planes):
        return "the compiled plane regularisers need CPU tensors"
    dtypes = {p.dtype for p in planes}
    if len(dtypes) != 1 or next(iter(dtypes)) not in _SUPPORTED_DTYPES:
        return f"the compiled plane regularisers need float32 or float64 planes of one dtype, got " \
               f"{sorted(map(str, dtypes))}"
    ok, reason = LIBRARY.available()
    return None if ok else reason


_logged_reasons: set[str] = set()


def log_fallback_once(reason: str) -> None:
    """Log (once per distinct reason and process) that the regularisers take the torch Function."""
    if reason in _logged_reasons:
        return
    _logged_reasons.add(reason)
    quiet = reason == disabled_by_env() or "CPU tensors" in reason or "dtype" in reason
    logger.log(logging.INFO if quiet else logging.WARNING,
               "plane regularisers: using the torch Function because %s", reason)


def _check(status: int) -> None:
    if status == 2:
        raise MemoryError("the compiled plane regularisers ran out of memory")
    if status != 0:
        raise RuntimeError(f"the compiled plane regularisers failed (status {status})")


def _has_term(plane: Tensor, smooth: float, l1: float) -> bool:
    return (smooth != 0 and plane.shape[-2] >= 3) or l1 != 0


def _non_overlapping_and_dense(tensor: Tensor) -> bool:
    """Whether the tensor's values fill one block of memory, each once, in some dimension order
    (then ``empty_like`` gives its gradient the same strides)."""
    expected = 1
    for stride, size in sorted((st, sz) for sz, st in zip(tensor.shape, tensor.stride()) if sz != 1):
        if stride != expected:
            return False
        expected *= size
    return True


def _dense(plane: Tensor) -> Tensor:
    """The plane itself when its gradient can share its strides (e.g. a view of the shared
    table), else a contiguous copy (expanded or sliced planes)."""
    return plane if _non_overlapping_and_dense(plane) else plane.contiguous()


def run_kernel(planes: Sequence[Tensor], smooth_weights: Sequence[float], l1_weights: Sequence[float],
               need_grad: Sequence[bool], num_threads: int | None = None) -> tuple[float, list[Tensor | None]]:
    """The total (a Python float, summed in double) and d total / d plane for each plane.

    Args:
        planes: [B, C, H, W] tensors of one dtype (float32 or float64) on the CPU, any strides.
        smooth_weights, l1_weights: one weight per plane (0 switches the term off).
        need_grad: per plane, whether to compute its gradient.
        num_threads: worker threads (default torch.get_num_threads()).
    Returns:
        (total, grads): grads[p] has plane p's shape and strides (dense planes; others
        contiguous), None where not needed or where the plane has no term.
    """
    planes = [_dense(p.detach()) for p in planes]
    grads = [torch.empty_like(p) if want and _has_term(p, s, l) else None
             for p, want, s, l in zip(planes, need_grad, smooth_weights, l1_weights)]
    count = len(planes)
    data = torch.tensor([p.data_ptr() for p in planes], dtype=torch.int64)
    grad_ptrs = torch.tensor([g.data_ptr() if g is not None else 0 for g in grads], dtype=torch.int64)
    sizes = torch.tensor([list(p.shape) for p in planes], dtype=torch.int64).reshape(-1)
    strides = torch.tensor([list(p.stride()) for p in planes], dtype=torch.int64).reshape(-1)
    smooth = torch.tensor([float(w) for w in smooth_weights], dtype=torch.float64)
    l1 = torch.tensor([float(w) for w in l1_weights], dtype=torch.float64)
    total = torch.zeros(1, dtype=torch.float64)
    threads = num_threads or torch.get_num_threads()
    status = getattr(LIBRARY.load(), f"rk_forward_{_SUPPORTED_DTYPES[planes[0].dtype]}")(
        count, data.data_ptr(), grad_ptrs.data_ptr(), sizes.data_ptr(), strides.data_ptr(), smooth.data_ptr(),
        l1.data_ptr(), int(threads), total.data_ptr())
    _check(status)
    return float(total.item()), grads


class _KernelRegularisation(torch.autograd.Function):
    """sum_p smooth[p] mean(second difference of p)^2 + l1[p] mean|1 - p|; gradients from the forward."""

    @staticmethod
    def forward(ctx, weights: tuple[tuple[float, ...], tuple[float, ...], int], *planes: Tensor) -> Tensor:
        smooth, l1, threads = weights
        total, grads = run_kernel(planes, smooth, l1, ctx.needs_input_grad[1:], threads)
        ctx.save_for_backward(*planes)
        ctx.weights = weights
        ctx.grads = grads  # handed to autograd by the first backward (see there)
        return planes[0].new_full((), total)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_total: Tensor):
        planes = ctx.saved_tensors  # raises if a plane was modified in place since the forward
        grads = ctx.grads
        if grads is None:
            # a second backward through a retained graph: the first one's gradients belong to
            # autograd now (it may have accumulated into them), so compute them again
            smooth, l1, threads = ctx.weights
            _, grads = run_kernel(planes, smooth, l1, ctx.needs_input_grad[1:], threads)
        # Ours alone from here: autograd may keep them as .grad and accumulate into them in place.
        ctx.grads = None
        scale = float(grad_total)
        if scale != 1.0:
            grads = [g.mul_(scale) if g is not None else None for g in grads]
        return (None, *grads)


def weighted_plane_regularisation(smooth_weights: Sequence[float], l1_weights: Sequence[float],
                                  planes: Sequence[Tensor], num_threads: int | None = None) -> Tensor:
    """0-dim total of the weighted regularisers over `planes` by the kernel (the caller checks
    `unusable_reason` first); differentiable with respect to every plane."""
    threads = int(num_threads or torch.get_num_threads())
    smooth, l1 = tuple(map(float, smooth_weights)), tuple(map(float, l1_weights))
    if not (torch.is_grad_enabled() and any(p.requires_grad for p in planes)):
        # no graph (evaluation, no_grad): the value alone, no gradient written
        total, _ = run_kernel(planes, smooth, l1, [False] * len(planes), threads)
        return planes[0].new_full((), total)
    return _KernelRegularisation.apply((smooth, l1, threads), *planes)
