"""The Gaussians' rows in a spatial (Morton, Z-order) order: neighbours in space, neighbours in memory.

Why: every step looks each Gaussian up in the HexPlane field (4 corners x 6 planes x 3 levels of
a ~25 MB channels-last table, forward and backward) and scatters its gradient back. In the order
a run leaves its rows (the initial cloud's order, clones and split children appended at the end)
consecutive rows address unrelated cells, so most reads and scattered writes miss the 1 MB L2
cache. Sorted by the Morton code of their canonical means, consecutive rows share cells. The
projection, binning and compositing read the rows in index order too and gain the same way.
Measured: docs/PROFILE.md, "Rows in spatial order".

It is a memory layout only: one permutation of every per-Gaussian parameter, Adam moment and
buffer (`GaussianModel.permute_rows`); a render of the permuted model equals the unpermuted one
up to float summation order. The trainer applies it after the model is created from its initial
cloud and after each densification step that rewrote the rows (trainer.py), so a resumed run
permutes at the same iterations as an uninterrupted one (a checkpoint stores the rows as they
are). `REFLOW4DGS_ROW_ORDER=0` keeps the rows in the order the run makes them.
"""
from __future__ import annotations

import torch
from torch import Tensor

from baselines.native_build import switched_off_by_env

ENV_SWITCH = "REFLOW4DGS_ROW_ORDER"
MORTON_BITS = 10  # cells per axis: 1024, finer than HexPlane's finest spatial planes (4 x 64-256)
BOX_QUANTILE = 0.001  # the box is the points' 0.1-99.9% range: a few far floaters do not squash the rest


def _spread_bits(values: Tensor) -> Tensor:
    """[N] int64 of MORTON_BITS-bit values -> the same bits at every third position (bit i -> 3i)."""
    x = values & 0x3FF
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    x = (x | (x << 2)) & 0x09249249
    return x


def morton_codes(points: Tensor) -> Tensor:
    """[N, 3] points -> [N] int64 Morton codes on a 1024^3 grid over the points' box.

    The box is the BOX_QUANTILE range per axis (points outside are clamped to its faces);
    non-finite coordinates are treated as the box's lower corner, so the codes are always defined.
    """
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"morton_codes: points must be [N, 3], got {list(points.shape)}")
    p = points.detach().to(torch.float32)
    if p.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=p.device)
    finite = torch.isfinite(p).all(dim=1)
    reference = p[finite] if bool(finite.any()) else torch.zeros(1, 3, device=p.device)
    if reference.shape[0] > 1:
        lo = torch.quantile(reference, BOX_QUANTILE, dim=0)
        hi = torch.quantile(reference, 1.0 - BOX_QUANTILE, dim=0)
    else:
        lo = hi = reference[0]
    span = torch.where(hi > lo, hi - lo, torch.ones_like(hi))
    cells = (1 << MORTON_BITS) - 1
    unit = ((p - lo) / span).clamp(0.0, 1.0)
    unit = torch.where(finite.unsqueeze(1), unit, torch.zeros_like(unit))
    q = torch.round(unit * cells).to(torch.int64)
    return _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << 1) | (_spread_bits(q[:, 2]) << 2)


def spatial_order(points: Tensor, deformed: Tensor | None = None) -> Tensor:
    """[N, 3] points -> [N] int64 permutation sorting them by Morton code (ties keep their order).

    deformed: [N] bool or None. Given, the rows it marks come last, each part in spatial order:
    the deformation reads and writes back only those rows (4DGS's deformation table; ReFlow's
    dynamic Gaussians), one contiguous block is cheaper to gather and scatter than rows spread
    through the table (interleaving ReFlow's static and dynamic rows made its step 4-11% slower).
    """
    codes = morton_codes(points)
    if deformed is not None:
        if deformed.shape != codes.shape:
            raise ValueError(f"spatial_order: deformed must be [{codes.shape[0]}], got {list(deformed.shape)}")
        codes = codes | (deformed.to(device=codes.device, dtype=torch.int64) << (3 * MORTON_BITS))
    return torch.argsort(codes, stable=True)


def order_rows(model) -> bool:
    """Permute `model`'s rows into spatial order of its canonical means, the deformed rows last;
    False (nothing done) when `REFLOW4DGS_ROW_ORDER=0` or the model has fewer than two Gaussians."""
    if switched_off_by_env("", ENV_SWITCH) or model.num_gaussians < 2:
        return False
    model.permute_rows(spatial_order(model.get_xyz, model.deformation_table))
    return True
