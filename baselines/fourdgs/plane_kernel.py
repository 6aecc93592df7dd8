"""Compiled CPU HexPlane lookup: the C++ kernel of csrc/plane_kernel.cpp for plane_lookup.py.

    lookup_forward(table [cells, C], coords [N, D], layout) -> products [N, (P / group) * C]
    lookup_backward(table, coords, layout, grad_out, want_axis, need_table)
        -> (grad_table [cells, C] or None, grad_coords [N, D] or None)

Same semantics as the torch path of plane_lookup.py (bilinear, align_corners=True, border
padding, groups of planes multiplied), which stays the oracle of the tests and the fallback. Why
compiled: the torch path spends about 25 small ops and a sort per plane per call (a few hundred
dispatches and temporaries for HexPlane's 12 planes), which made the lookup about a third of a
fine iteration on the embedded scene; the kernel does one pass over the points. The backward is
bitwise deterministic across thread counts (see the C++ header).

Building and caching as every compiled kernel here (baselines/native_build.py). Switches:
`REFLOW4DGS_PLANE_KERNEL=0` (or false/off/no) keeps the torch path for the lookups;
`REFLOW4DGS_CPU_KERNEL=0` switches off every compiled CPU kernel, this one included. Without a
compiler or when the build fails, the torch path runs and the reason is logged once. Dtypes:
float32 and float64 on CPU (others take the torch path).
"""
from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor

from baselines import native_build

logger = logging.getLogger(__name__)

ENV_SWITCH = "REFLOW4DGS_PLANE_KERNEL"
ENV_ALL_KERNELS = "REFLOW4DGS_CPU_KERNEL"
SOURCE = Path(__file__).resolve().parent / "csrc" / "plane_kernel.cpp"
ABI_VERSION = 1  # must equal kAbiVersion in the C++ source
_SUPPORTED_DTYPES = {torch.float32: "f32", torch.float64: "f64"}


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    common = [ptr, ptr, i64, i64, i64, ptr, ptr, ptr, ptr, ptr, i64, i64, i64]
    for suffix in _SUPPORTED_DTYPES.values():
        forward = getattr(lib, f"pk_forward_{suffix}")
        forward.argtypes = common + [ptr]
        forward.restype = ctypes.c_int
        backward = getattr(lib, f"pk_backward_{suffix}")
        backward.argtypes = common + [ptr, ptr, ptr, ptr]
        backward.restype = ctypes.c_int
    native_build.check_abi_version(lib, "pk_abi_version", ABI_VERSION, "plane kernel")
    return lib


LIBRARY = native_build.NativeLibrary("plane_kernel", SOURCE, ABI_VERSION, _bind)


def disabled_by_env() -> str | None:
    """The reason the plane kernel is switched off by the environment, or None."""
    return native_build.switched_off_by_env("the compiled plane lookup", ENV_SWITCH, ENV_ALL_KERNELS)


def unusable_reason(table: Tensor, coords_dtype: torch.dtype) -> str | None:
    """None when the kernel can run a lookup on `table` with coordinates of `coords_dtype`, else why not."""
    reason = disabled_by_env()
    if reason is not None:
        return reason
    if table.device.type != "cpu":
        return f"the compiled plane lookup needs CPU tensors, got {table.device}"
    if table.dtype not in _SUPPORTED_DTYPES or coords_dtype != table.dtype:
        return f"the compiled plane lookup needs float32 or float64 planes and coordinates of the same dtype, got " \
               f"{table.dtype} and {coords_dtype}"
    ok, reason = LIBRARY.available()
    return None if ok else reason


_logged_reasons: set[str] = set()


def log_fallback_once(reason: str) -> None:
    """Log (once per distinct reason and process) that the lookups take the torch path."""
    if reason in _logged_reasons:
        return
    _logged_reasons.add(reason)
    level = logging.INFO if reason == disabled_by_env() or "CPU tensors" in reason else logging.WARNING
    logger.log(level, "plane lookup: using the torch path because %s", reason)


@functools.lru_cache(maxsize=64)
def _layout_arrays(u_axis: tuple[int, ...], v_axis: tuple[int, ...], width: tuple[int, ...],
                   height: tuple[int, ...], offset: tuple[int, ...]) -> tuple[Tensor, ...]:
    """The layout's per-plane integers as int64 arrays the kernel reads (cached per layout)."""
    return tuple(torch.tensor(values, dtype=torch.int64) for values in (u_axis, v_axis, width, height, offset))


def _layout_args(layout) -> list[int]:
    arrays = _layout_arrays(layout.u_axis, layout.v_axis, layout.width, layout.height, layout.offset)
    return [a.data_ptr() for a in arrays] + [layout.num_planes, layout.group]


def _check(status: int, stage: str) -> None:
    if status == 2:
        raise MemoryError(f"the compiled plane lookup ran out of memory in its {stage} pass")
    if status != 0:
        raise RuntimeError(f"the compiled plane lookup failed in its {stage} pass (status {status})")


def lookup_forward(table: Tensor, coords: Tensor, layout, num_threads: int | None = None) -> Tensor:
    """[N, (P / group) * C] group products of the planes' bilinear samples.

    Args:
        table: [num_cells, C] contiguous channels-last plane table (not differentiated here).
        coords: [N, D] coordinates in [-1, 1], same dtype as the table.
        layout: the planes' ``plane_lookup.PlaneLayout``.
        num_threads: worker threads (default torch.get_num_threads()).
    """
    lib = LIBRARY.load()
    table, coords = table.detach().contiguous(), coords.detach().contiguous()
    n, dims = coords.shape
    channels = table.shape[1]
    out = torch.empty(n, (layout.num_planes // layout.group) * channels, dtype=table.dtype)
    threads = num_threads or torch.get_num_threads()
    status = getattr(lib, f"pk_forward_{_SUPPORTED_DTYPES[table.dtype]}")(
        table.data_ptr(), coords.data_ptr(), n, dims, channels, *_layout_args(layout), threads, out.data_ptr())
    _check(status, "forward")
    return out


def lookup_backward(table: Tensor, coords: Tensor, layout, grad_out: Tensor, want_axis: Sequence[bool] | None,
                    need_table: bool, num_threads: int | None = None) -> tuple[Tensor | None, Tensor | None]:
    """Gradients of ``sum(grad_out * lookup_forward(table, coords))``.

    Args:
        table, coords, layout: as for ``lookup_forward``.
        grad_out: [N, (P / group) * C].
        want_axis: [D] flags, which coordinates get a gradient; None for none.
        need_table: whether to compute the table gradient.
    Returns:
        (grad_table [num_cells, C] or None, grad_coords [N, D] or None); coordinates not wanted
        get zeros in grad_coords.
    """
    lib = LIBRARY.load()
    table, coords = table.detach().contiguous(), coords.detach().contiguous()
    grad_out = grad_out.to(table.dtype).contiguous()
    n, dims = coords.shape
    grad_table = torch.zeros_like(table) if need_table else None
    grad_coords = torch.zeros_like(coords) if want_axis is not None and any(want_axis) else None
    if grad_table is None and grad_coords is None:
        return None, None
    wants = torch.tensor([bool(w) for w in want_axis] if grad_coords is not None else [0] * dims, dtype=torch.uint8)
    threads = num_threads or torch.get_num_threads()
    status = getattr(lib, f"pk_backward_{_SUPPORTED_DTYPES[table.dtype]}")(
        table.data_ptr(), coords.data_ptr(), n, dims, table.shape[1], *_layout_args(layout), threads,
        grad_out.data_ptr(), wants.data_ptr(),
        grad_table.data_ptr() if grad_table is not None else None,
        grad_coords.data_ptr() if grad_coords is not None else None)
    _check(status, "backward")
    return grad_table, grad_coords
