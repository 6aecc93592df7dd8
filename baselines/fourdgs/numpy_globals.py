"""The numpy scalar types a 4DGaussians checkpoint holds, allowed through ``torch.load(weights_only=True)``.

4DGS's ``chkpnt_<stage>_<N>.pth`` is ``torch.save((gaussians.capture(), iteration))``; its
optimizer state carries learning rates computed with numpy (``get_expon_lr_func`` returns
``numpy.float64``) and ``spatial_lr_scale`` may be a numpy float. Unpickling those needs
``numpy._core.multiarray.scalar`` (``numpy.core.multiarray.scalar`` in files written by numpy 1.x),
``numpy.dtype`` and numpy 2's per-dtype classes. Only these are allowed, never arbitrary objects
(no ``weights_only=False``).
"""
from __future__ import annotations

import contextlib
from typing import Any, Iterator

import numpy as np
import torch

_SCALAR_DTYPES = ("float16", "float32", "float64", "int8", "int16", "int32", "int64",
                  "uint8", "uint16", "uint32", "uint64", "bool")


def numpy_scalar_globals() -> list[Any]:
    """Entries for ``torch.serialization.safe_globals``: objects, or (object, pickled name) pairs."""
    core = getattr(np, "_core", None) or np.core  # numpy 2 / numpy 1
    scalar = core.multiarray.scalar
    entries: list[Any] = [scalar, (scalar, "numpy.core.multiarray.scalar"),
                          (scalar, "numpy._core.multiarray.scalar"), np.dtype]
    dtypes = getattr(np, "dtypes", None)  # numpy >= 1.25: one class per dtype
    if dtypes is not None:
        entries += [type(np.dtype(name)) for name in _SCALAR_DTYPES]
    return entries


@contextlib.contextmanager
def allow_numpy_scalars() -> Iterator[None]:
    """Within the block, ``torch.load(weights_only=True)`` accepts numpy scalars (and only them)."""
    with torch.serialization.safe_globals(numpy_scalar_globals()):
        yield
