"""Backend registry: which projection and compositing functions each backend name uses.

A backend is a pair of stage functions with the signatures below. Backends are resolved lazily
so that importing the rasterizer never imports gsplat or builds the CPU kernel.

    project(means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d) -> Projection
    composite(projection, opacities [N], features [N, C], width, height)
        -> (image [H, W, C] without background, alpha [H, W, 1])
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .projection import Projection, project_gaussians_torch

ProjectFn = Callable[..., Projection]
CompositeFn = Callable[[Projection, Tensor, Tensor, int, int], "tuple[Tensor, Tensor]"]

BACKEND_NAMES = ("reference", "cpu", "gsplat")


@dataclass(frozen=True)
class Backend:
    name: str
    project: ProjectFn
    composite: CompositeFn


def _composite_reference(projection: Projection, opacities: Tensor, features: Tensor, width: int, height: int):
    from .composite_reference import composite_reference

    return composite_reference(projection, opacities, features, width, height)


def _composite_cpu(projection: Projection, opacities: Tensor, features: Tensor, width: int, height: int):
    # The compiled kernel when it builds and fits the tensors; else the torch tiled path, with
    # the reason logged once (no compiler, build failure, REFLOW4DGS_CPU_KERNEL=0, dtype, device).
    from .kernel import composite_kernel, log_fallback_once, unusable_reason

    reason = unusable_reason(features)
    if reason is None:
        return composite_kernel(projection, opacities, features, width, height)
    log_fallback_once(reason)
    from .composite_tiled import composite_tiled

    return composite_tiled(projection, opacities, features, width, height)


def _project_cpu(means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d) -> Projection:
    # The compiled projection when it builds and fits the tensors; else the torch twin, with the
    # reason logged once (as the compositor)
    from .project_kernel import project_gaussians_cpu

    return project_gaussians_cpu(means, quats, scales, viewmat, K, width, height, opacities, near, far, eps2d)


def gsplat_unavailable_reason(device: torch.device) -> str | None:
    """None when the gsplat backend can run on `device`, else the reason it cannot."""
    if device.type != "cuda":
        return f"the gsplat backend needs CUDA tensors, got tensors on {device}"
    if not torch.cuda.is_available():
        return "the gsplat backend needs CUDA, but torch.cuda.is_available() is False"
    try:
        importlib.import_module("gsplat")
    except Exception as exc:  # ImportError, or a broken CUDA build raising at import
        return f"gsplat is not importable ({exc.__class__.__name__}: {exc}); install the 'cuda' extra"
    return None


def _gsplat_backend() -> Backend:
    from . import gsplat_backend

    return Backend("gsplat", gsplat_backend.project_gaussians_gsplat, gsplat_backend.composite_gsplat)


def resolve_backend(name: str, device: torch.device) -> Backend:
    """Return the backend for `name` ("auto" picks gsplat on usable CUDA, else cpu).

    Raises:
        ValueError: unknown name, or gsplat requested where it cannot run (with the reason).
    """
    if name == "auto":
        name = "gsplat" if gsplat_unavailable_reason(device) is None else "cpu"
    if name == "reference":
        return Backend("reference", project_gaussians_torch, _composite_reference)
    if name == "cpu":
        return Backend("cpu", _project_cpu, _composite_cpu)
    if name == "gsplat":
        reason = gsplat_unavailable_reason(device)
        if reason is not None:
            raise ValueError(f"backend='gsplat' cannot run: {reason}")
        return _gsplat_backend()
    raise ValueError(f"backend must be one of {('auto',) + BACKEND_NAMES}, got {name!r}")


def available_backends(device: torch.device | str = "cpu") -> list[str]:
    """Backend names usable for tensors on `device`."""
    device = torch.device(device)
    names = ["reference", "cpu"]
    if gsplat_unavailable_reason(device) is None:
        names.append("gsplat")
    return names
