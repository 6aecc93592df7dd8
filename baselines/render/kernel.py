"""Compiled CPU compositor: the C++ kernel of csrc/raster_kernel.cpp behind a torch autograd Function.

    composite_kernel(projection, opacities [N], features [N, C], width, height, num_threads=None)
        -> (image [H, W, C] without background, alpha [H, W, 1])

Only the compositing stage is compiled; projection stays in torch, and the gradients this module
returns for means2d, conics, opacities and features flow on through autograd to means, quats and
scales (and reach `meta.means2d.grad` for densification). The rules and the oracle are those of
composite_reference.py; the C++ header comment explains the tiling, the early exits and why the
backward pass is bitwise deterministic across thread counts.

Building: a plain C++17 shared library compiled on first use and cached, as every compiled kernel
here (baselines/native_build.py: compiler lookup, cache location and key, atomic builds). The AVX2
pixel loops are compiled as separate functions (a target attribute) and chosen at run time when
the CPU has AVX2; every other CPU, and float64, runs the portable variant, which gives bitwise
identical results.

Switches: `REFLOW4DGS_CPU_KERNEL=0` (or false/off/no) makes the cpu backend use the torch tiled
path. Without a compiler, or when the build fails, `kernel_available()` returns (False, reason)
and the cpu backend falls back likewise, logging the reason once. `REFLOW4DGS_KERNEL_ISA=portable`
(or avx2; default auto) forces a variant of the pixel loops, for tests and comparisons.
`REFLOW4DGS_ACTIVE_CHANNELS=0` makes the backward pass process every channel, also trailing ones
whose upstream gradient is zero (by default they are left out: same gradients, less work).

Dtypes: float32 and float64 both run compiled (the kernel is templated on the scalar type);
bfloat16 and non-CPU tensors take the torch tiled path (float16 is rejected by validation).
"""
from __future__ import annotations

import ctypes
import logging
import os
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from baselines import native_build
from baselines.native_build import ENV_CACHE_DIR, KernelUnavailable, find_compiler  # noqa: F401 (public names)

from .projection import Projection
from .tiles import TILE_SIZE, TileBins

logger = logging.getLogger(__name__)

ENV_SWITCH = "REFLOW4DGS_CPU_KERNEL"
ENV_ISA = "REFLOW4DGS_KERNEL_ISA"
ENV_ACTIVE_CHANNELS = "REFLOW4DGS_ACTIVE_CHANNELS"  # 0/false/off/no: the backward runs every channel
# Instruction-set variants of the kernel's pixel loops (the `isa` argument of its entry points).
ISA_CODES = {"auto": 0, "portable": 1, "avx2": 2}
SOURCE = Path(__file__).resolve().parent / "csrc" / "raster_kernel.cpp"
ABI_VERSION = 2  # must equal kAbiVersion in the C++ source
_SUPPORTED_DTYPES = {torch.float32: "f32", torch.float64: "f64"}


def disabled_by_env() -> str | None:
    """The reason the kernel is switched off by the environment, or None."""
    return native_build.switched_off_by_env("the compiled CPU kernel", ENV_SWITCH)


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    common = [ptr, ptr, ptr, ptr, ptr, i64, i64, ptr, ptr, i64, i64, i64, i64, i64]
    for suffix in _SUPPORTED_DTYPES.values():
        forward = getattr(lib, f"rk_forward_{suffix}")
        forward.argtypes = common + [ptr, ptr, ptr, ptr]
        forward.restype = ctypes.c_int
        backward = getattr(lib, f"rk_backward_{suffix}")
        backward.argtypes = common + [ptr, ptr, ptr, ptr, ptr, ptr, ptr, ptr]
        backward.restype = ctypes.c_int
        count = getattr(lib, f"rk_bin_count_{suffix}")
        count.argtypes = [ptr, ptr, ptr, i64, i64, i64, i64, ptr]
        count.restype = i64
        fill = getattr(lib, f"rk_bin_fill_{suffix}")
        fill.argtypes = [ptr, ptr, ptr, ptr, i64, i64, i64, i64, ptr, ptr]
        fill.restype = ctypes.c_int
    lib.rk_isa_supported.argtypes = [i64]
    lib.rk_isa_supported.restype = ctypes.c_int
    lib.rk_raw_alpha_f32.argtypes = [ptr, ptr, ptr, i64, i64]
    lib.rk_raw_alpha_f32.restype = ctypes.c_int
    lib.rk_libm_expf.argtypes = [ptr, ptr, i64]
    lib.rk_libm_expf.restype = None
    native_build.check_abi_version(lib, "rk_abi_version", ABI_VERSION, "kernel")
    return lib


LIBRARY = native_build.NativeLibrary("raster_kernel", SOURCE, ABI_VERSION, _bind)


def library_path(compiler: str) -> Path:
    """Cache path of the compositing library built with `compiler`."""
    return LIBRARY.path(compiler)


def load_library() -> ctypes.CDLL:
    """The loaded kernel library, building it on first use (one attempt per process).

    Raises:
        KernelUnavailable: with the reason (no compiler, build failure, unwritable cache, ...).
    """
    return LIBRARY.load()


def kernel_available() -> tuple[bool, str]:
    """(True, library path) when the compiled kernel can run, else (False, the reason).

    Builds the kernel on the first call in a process when needed; honours REFLOW4DGS_CPU_KERNEL.
    """
    reason = disabled_by_env()
    if reason is not None:
        return False, reason
    return LIBRARY.available()


def unusable_reason(features: Tensor) -> str | None:
    """None when composite_kernel can handle tensors like `features`, else why not."""
    if features.device.type != "cpu":
        return f"the compiled CPU kernel needs CPU tensors, got {features.device}"
    if features.dtype not in _SUPPORTED_DTYPES:
        return f"the compiled CPU kernel supports float32 and float64, got {features.dtype}"
    ok, reason = kernel_available()
    return None if ok else reason


_logged_reasons: set[str] = set()


def log_fallback_once(reason: str) -> None:
    """Log (once per distinct reason and process) that the cpu backend uses the torch tiled path."""
    if reason in _logged_reasons:
        return
    _logged_reasons.add(reason)
    level = logging.INFO if reason == disabled_by_env() else logging.WARNING
    logger.log(level, "cpu backend: using the torch tiled compositor because %s", reason)


def _ptr(t: Tensor) -> int:
    return t.data_ptr()


class _CompositeKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, radii, offsets, gaussian_ids,
                width: int, height: int, tile_size: int, num_threads: int, isa: int):
        lib = load_library()
        suffix = _SUPPORTED_DTYPES[features.dtype]
        means2d, conics, opacities, features = (t.detach().contiguous() for t in (means2d, conics, opacities, features))
        radii = radii.detach().to(torch.int32).contiguous()
        offsets = offsets.to(torch.int64).contiguous()
        gaussian_ids = gaussian_ids.to(torch.int64).contiguous()
        n, channels = features.shape
        image = torch.empty(height, width, channels, dtype=features.dtype)
        alpha = torch.empty(height, width, 1, dtype=features.dtype)
        transmittance = torch.empty(height, width, dtype=torch.float64)
        last = torch.empty(height, width, dtype=torch.int32)
        status = getattr(lib, f"rk_forward_{suffix}")(
            _ptr(means2d), _ptr(conics), _ptr(opacities), _ptr(features), _ptr(radii), n, channels,
            _ptr(offsets), _ptr(gaussian_ids), width, height, tile_size, num_threads, isa,
            _ptr(image), _ptr(alpha), _ptr(transmittance), _ptr(last),
        )
        _check_status(status, "forward")
        ctx.save_for_backward(means2d, conics, opacities, features, radii, offsets, gaussian_ids, transmittance, last)
        ctx.geometry = (width, height, tile_size, num_threads, isa)
        return image, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_image, grad_alpha):
        means2d, conics, opacities, features, radii, offsets, gaussian_ids, transmittance, last = ctx.saved_tensors
        width, height, tile_size, num_threads, isa = ctx.geometry
        lib = load_library()
        suffix = _SUPPORTED_DTYPES[features.dtype]
        n, channels = features.shape
        grad_image = grad_image.to(features.dtype)
        grad_alpha = grad_alpha.to(features.dtype).contiguous()
        # Trailing channels with an all-zero upstream gradient add nothing to any gradient but their
        # own (zero) feature gradient: leave them out of the kernel's per-pair work. A loss that
        # reads the colours only (the densification statistic's pass beside a plugin's channels)
        # then costs what the colours alone cost.
        off = native_build.switched_off_by_env("leaving out zero-gradient channels", ENV_ACTIVE_CHANNELS)
        active = channels if off is not None else active_channels(grad_image)
        if active < channels:
            features = features[:, :active].contiguous()
            grad_image = grad_image[..., :active]
        grad_image = grad_image.contiguous()
        # The kernel writes every entry (zero for Gaussians that touch no pixel).
        g_means2d = torch.empty_like(means2d)
        g_conics = torch.empty_like(conics)
        g_opacities = torch.empty_like(opacities)
        g_features = torch.empty_like(features)  # [N, active]
        status = getattr(lib, f"rk_backward_{suffix}")(
            _ptr(means2d), _ptr(conics), _ptr(opacities), _ptr(features), _ptr(radii), n, active,
            _ptr(offsets), _ptr(gaussian_ids), width, height, tile_size, num_threads, isa,
            _ptr(transmittance), _ptr(last), _ptr(grad_image), _ptr(grad_alpha),
            _ptr(g_means2d), _ptr(g_conics), _ptr(g_opacities), _ptr(g_features),
        )
        _check_status(status, "backward")
        g_features = torch.nn.functional.pad(g_features, (0, channels - active))  # the left-out channels: 0
        needs = ctx.needs_input_grad
        grads = (g_means2d, g_conics, g_opacities, g_features)
        return tuple(g if needs[i] else None for i, g in enumerate(grads)) + (None,) * 8


def active_channels(grad_image: Tensor) -> int:
    """The channels the backward pass must process: all up to the last one whose upstream gradient
    [H, W, C] has a non-zero entry (at least 1, the kernel's minimum)."""
    nonzero = grad_image.ne(0).flatten(0, -2).any(dim=0).nonzero()
    return max(1, int(nonzero[-1]) + 1) if nonzero.numel() else 1


def _check_status(status: int, stage: str) -> None:
    if status == 2:
        raise MemoryError(f"the compiled CPU kernel ran out of memory in its {stage} pass")
    if status == 4:
        raise RuntimeError(f"the compiled CPU kernel's {stage} pass was asked for an instruction set this CPU lacks")
    if status != 0:
        raise RuntimeError(f"the compiled CPU kernel failed in its {stage} pass (status {status})")


def requested_isa() -> str:
    """The kernel variant asked for by $REFLOW4DGS_KERNEL_ISA: "auto" (default), "portable" or "avx2".

    Raises:
        ValueError: the variable holds another value.
    """
    value = os.environ.get(ENV_ISA, "").strip().lower() or "auto"
    if value not in ISA_CODES:
        raise ValueError(f"{ENV_ISA}={os.environ[ENV_ISA]!r} is not one of {', '.join(ISA_CODES)}")
    return value


def isa_supported(isa: str) -> bool:
    """Whether this CPU can run the kernel variant `isa` ("portable" always can).

    Raises:
        KernelUnavailable: the kernel cannot be built or loaded.
    """
    return bool(load_library().rk_isa_supported(ISA_CODES[isa]))


def kernel_isa(dtype: torch.dtype = torch.float32) -> str:
    """The variant of the pixel loops that runs for tensors of `dtype`: "avx2" or "portable".

    "auto" picks AVX2 for float32 where the CPU has it; float64 always runs the portable
    variant. Both give bitwise identical results.

    Raises:
        ValueError: $REFLOW4DGS_KERNEL_ISA is invalid, or asks for AVX2 on a CPU without it.
        KernelUnavailable: the kernel cannot be built or loaded.
    """
    isa = requested_isa()
    if isa == "avx2" and not isa_supported("avx2"):
        raise ValueError(f"{ENV_ISA}=avx2 but this CPU does not support AVX2")
    if isa == "auto":
        isa = "avx2" if dtype == torch.float32 and isa_supported("avx2") else "portable"
    return "portable" if dtype != torch.float32 else isa


def bin_gaussians_compiled(projection: Projection, width: int, height: int, tile_size: int = TILE_SIZE) -> TileBins:
    """Compiled equivalent of tiles.bin_gaussians: the same per-tile, front-to-back lists.

    A radix sort by depth and a counting sort into tiles in C++ (O(N + M) for M intersections)
    instead of torch's sort of all intersection keys; it also avoids a dozen small torch ops per
    view.

    Args:
        projection: CPU projection of N Gaussians (means2d, radii, depths, visible are read).
        width, height: image size in pixels.
    Returns:
        TileBins with offsets [tiles + 1] and gaussian_ids [M] (int64).
    Raises:
        KernelUnavailable: the kernel cannot be built or loaded.
    """
    lib = load_library()
    means2d = projection.means2d.detach().contiguous()
    suffix = _SUPPORTED_DTYPES.get(means2d.dtype)
    if suffix is None or means2d.device.type != "cpu":
        raise ValueError(f"bin_gaussians_compiled needs float32/float64 CPU tensors, got {means2d.dtype} "
                         f"on {means2d.device}")
    depths = projection.depths.detach().to(means2d.dtype).contiguous()
    radii = projection.radii.detach().to(torch.int32).contiguous()
    visible = projection.visible.detach().to(torch.uint8).contiguous()
    n = means2d.shape[0]
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    offsets = torch.empty(tiles_x * tiles_y + 1, dtype=torch.int64)
    total = getattr(lib, f"rk_bin_count_{suffix}")(_ptr(means2d), _ptr(radii), _ptr(visible), n, width, height,
                                                   tile_size, _ptr(offsets))
    if total < 0:
        raise RuntimeError("the compiled CPU kernel failed while counting tile intersections")
    gaussian_ids = torch.empty(total, dtype=torch.int64)
    status = getattr(lib, f"rk_bin_fill_{suffix}")(_ptr(means2d), _ptr(radii), _ptr(visible), _ptr(depths), n, width,
                                                  height, tile_size, _ptr(offsets), _ptr(gaussian_ids))
    _check_status(status, "binning")
    return TileBins(tile_size, tiles_x, tiles_y, offsets, gaussian_ids)


def composite_kernel(
    projection: Projection,
    opacities: Tensor,
    features: Tensor,
    width: int,
    height: int,
    num_threads: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Tiled front-to-back compositing in compiled C++ (same rules and outputs as the reference).

    Args:
        projection: projection stage output for N Gaussians (means2d, conics, radii, depths and
            visible are read; gradients flow back to means2d and conics).
        opacities: [N] activated opacities. features: [N, C], any C >= 1.
        width, height: image size in pixels.
        num_threads: worker threads (default torch.get_num_threads()); results are bitwise
            identical for every value.
    Returns:
        (image [H, W, C] without background, alpha [H, W, 1]), differentiable w.r.t. means2d,
        conics, opacities and features.
    Raises:
        KernelUnavailable: the kernel cannot be built or loaded (see kernel_available()).
        ValueError: tensors not on the CPU, not float32/float64, or of mixed dtypes/shapes.
    """
    tensors = {"means2d": projection.means2d, "conics": projection.conics, "depths": projection.depths,
               "opacities": opacities, "features": features}
    dtype = projection.means2d.dtype
    if dtype not in _SUPPORTED_DTYPES:
        raise ValueError(f"composite_kernel supports float32 and float64, means2d is {dtype}")
    for name, t in tensors.items():
        if t.device.type != "cpu":
            raise ValueError(f"composite_kernel needs CPU tensors, {name} is on {t.device}")
        if t.dtype != dtype:
            raise ValueError(f"composite_kernel needs tensors of one dtype: means2d is {dtype} but {name} is {t.dtype}")
    n = projection.means2d.shape[0]
    if features.dim() != 2 or features.shape[0] != n or features.shape[1] < 1 or opacities.shape != (n,):
        raise ValueError(f"composite_kernel needs opacities [N] and features [N, C>=1] with N={n}, got "
                         f"{tuple(opacities.shape)} and {tuple(features.shape)}")
    threads = int(num_threads) if num_threads is not None else torch.get_num_threads()
    if threads < 1:
        raise ValueError(f"num_threads must be >= 1, got {threads}")
    isa = ISA_CODES[kernel_isa(dtype)]
    bins = bin_gaussians_compiled(projection, int(width), int(height))
    return _CompositeKernel.apply(
        projection.means2d, projection.conics, opacities, features, projection.radii, bins.offsets,
        bins.gaussian_ids, int(width), int(height), bins.tile_size, threads, isa,
    )
