"""Anchored alignment in inverse depth: monocular disparity at the scene's scale, cameras fixed.

    states, report = align_inverse(provider, frames, weights, fits, anchors, window=4, iterations=50)

A monocular network's disparity d_n is inverse depth up to a per-frame affine map,
1 / z = s_n d_n + o_n. The DUSt3R-style alignment (alignment.py) has a per-frame DEPTH scale and
shift, which cannot represent that map, and its loss (3D distance relative to the point's own,
free depth) does not exclude shrinking every depth toward the cameras. Here the unknowns are the
inverse-depth maps themselves:

1. Initialisation, per frame, closed form (reflow_plugin.disparity.fit_frames): a robust fit of
   (s_n, o_n) to the host's sparse metric points that project into the frame outside its mask;
   else the dataset's near/far bounds; else a neighbour's depth range.
2. Refinement (Adam, cosine rate, cameras fixed). u_n = exp(a_n) (s_n d_n + o_n) + b_n m_n with
   (a_n, b_n) starting at 0 and m_n the frame's median initial inverse depth, minimising

       L = sum_k v_k rho(u_n(d_k) z_k - 1) / sum_k v_k        anchors: sparse point k at depth z_k, vote v_k
         + lambda mean_(i,j),p rho(u_j(q) Z_ij(p) - 1)        views: pixel p of frame i, placed at
                                                             1 / u_i(p), seen by camera j at pixel
                                                             q with depth Z_ij(p)

   rho(r) = delta^2 log(1 + (r / delta)^2) (Cauchy, delta = 0.05: occlusions and the monocular
   error's edges are outliers), pairs (i, j) at most `window` frames apart in time, both ways.
   The anchor term counts each sparse point with its vote (reflow_plugin.disparity.coverage_weights:
   one vote per image region of its frame, as in the per-frame fits): a cluster of points on one
   textured patch must not outweigh the rest of the frame here either.

   Scale. The anchor residuals are relative to a FIXED depth (the sparse point's): multiplying
   every u by c costs (c - 1) on every anchor, so with sparse points the trivial solution (all
   depths shrinking toward the cameras) is not a minimum. The view term alone does NOT fix the
   scale: it is relative to the other frame's prediction, which scales with it; on a plane a
   common scale leaves it exactly unchanged, and a cloud pushed out of the views empties its
   weighted mean (loss 0). Measured (2026-11-26), three cameras on a plane, no sparse points:
   started 2x too near, the depth stayed at 0.49 of the truth (view residual 1e-7); started right
   on average (+-5% per frame), 50 steps drifted it to 0.981-0.983; the real-priors scenes with
   the bounds alone drifted to 0.89-0.94 of the true depth. So without anchors (bounds /
   neighbour fits only) a gauge term holds the common scale where the initial fits put it (the
   same cases: 0.9999-1.0015, and 1.015-1.040 on the scenes):

       + SCALE_WEIGHT (mean_n log(exp(a_n) + b_n))^2

   (exp(a_n) + b_n: the refined over the initial median inverse depth of frame n); the frames'
   scales relative to each other stay free for the view term. The report names the anchor.

Degenerate cases: a frame whose refined map puts more than MAX_BEHIND of its pixels behind the
camera keeps its initial fit (reported); pixels with u <= 0 or beyond `max_depth` (the bounds' far
x BOUNDS_SLACK, else 10 x the frame's median depth) carry no depth; no pair with evidence: the
initial fits are returned as they are.
"""
from __future__ import annotations

import logging
import math
import sys
import time
from typing import Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..disparity import BOUNDS_SLACK, MAX_BEHIND, FrameFit, camera_bounds
from .alignment import FrameState
from .geometry import rays as grid_rays
from .providers import PointmapProvider

log = logging.getLogger(__name__)

DELTA = 0.05
SCALE_WEIGHT = 1.0  # gauge term without sparse points (module docstring)
VIEW_WEIGHT = 1.0
MAX_PIXELS = 256  # source pixels per frame in the view term (seeded subsample)
FAR_FACTOR = 10.0  # max depth without bounds: this x the frame's median depth


def _rho(r: torch.Tensor) -> torch.Tensor:
    return DELTA ** 2 * torch.log1p((r / DELTA) ** 2)


def _max_depth(provider: PointmapProvider, n: int, fit: FrameFit, d: np.ndarray) -> float:
    bounds = camera_bounds(provider.cameras[n])
    if bounds is not None:
        return bounds[1] * BOUNDS_SLACK
    z = fit.depth(d)
    return FAR_FACTOR * float(np.nanmedian(z)) if np.isfinite(z).any() else math.inf


def _votes(pairs: tuple | None, count: int) -> np.ndarray:
    """[count] votes of one frame's anchor pairs: the third entry when given, else one each."""
    if pairs is not None and len(pairs) > 2:
        return np.asarray(pairs[2], np.float64).reshape(-1)
    return np.ones(count)


def _pairs(frames: Sequence[int], window: int) -> list[tuple[int, int]]:
    """Directed pairs (i, j) at most `window` positions apart in `frames` (time order)."""
    return [(frames[a], frames[b]) for a in range(len(frames)) for b in range(len(frames))
            if a != b and abs(a - b) <= window]


def align_inverse(provider: PointmapProvider, frames: Sequence[int], weights: Mapping[int, np.ndarray],
                  fits: Mapping[int, FrameFit], anchors: Mapping[int, tuple[np.ndarray, ...]],
                  window: int = 4, iterations: int = 50, lr: float = 0.02, progress: bool = False,
                  device: torch.device | str = "cpu", seed: int = 0) -> tuple[dict[int, FrameState], dict]:
    """Per-frame inverse-depth maps of `frames` (camera indices sorted by time).

    weights: per frame [h, w] on the provider's grid (0 on dynamic pixels); fits: the initial
    FrameFit of every frame (usable); anchors: per frame (d [K], z [K]) or (d [K], z [K], votes [K])
    sparse pairs (may be empty; without votes each pair counts once).
    Returns ({frame: FrameState(inverse=True)}, report with residuals, sources and seconds).
    """
    start = time.perf_counter()
    frames = list(frames)
    rows, cols = provider.grid()
    h, w = len(rows), len(cols)
    index = {n: k for k, n in enumerate(frames)}
    D, V, M, max_depth = [], [], [], []
    for n in frames:
        d, conf = provider.inverse_depth(n)
        d = np.asarray(d, np.float64)
        u0 = fits[n].inverse(d)
        valid = np.isfinite(d) & (np.nan_to_num(np.asarray(conf, np.float64)) > 0) & (u0 > 0)
        D.append(np.where(valid, d, 0.0))
        V.append(valid & (np.asarray(weights[n]) > 0))
        M.append(float(np.median(u0[valid])) if valid.any() else 1.0)
        max_depth.append(_max_depth(provider, n, fits[n], d))
    T = lambda a, dtype=torch.float32: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
    Dt, Vt = T(D), T(V)  # [F, h, w]
    s0, o0, m = T([fits[n].scale for n in frames]), T([fits[n].shift for n in frames]), T(M)
    R = T([provider.viewmats[n][:3, :3] for n in frames])
    t = T([provider.viewmats[n][:3, 3] for n in frames])
    Kt = T([provider.K[n] for n in frames])
    rays = T([grid_rays(provider.K[n], rows, cols).reshape(-1, 3) for n in frames])  # [F, P, 3]
    # anchors, concatenated
    fa = np.concatenate([np.full(len(anchors.get(n, ([], []))[0]), index[n]) for n in frames] + [np.zeros(0)])
    da = np.concatenate([np.asarray(anchors.get(n, ([], []))[0], np.float64) for n in frames] + [np.zeros(0)])
    za = np.concatenate([np.asarray(anchors.get(n, ([], []))[1], np.float64) for n in frames] + [np.zeros(0)])
    va = np.concatenate([_votes(anchors.get(n), len(anchors.get(n, ([], []))[0])) for n in frames] + [np.zeros(0)])
    fa, da, za, va = T(fa, torch.long), T(da), T(za), T(va)
    scale_anchor = "sparse points" if len(fa) else "initial fits' common scale (no sparse point)"
    if not len(fa):
        log.info("inverse-depth refinement: no sparse point; the common scale is held at the initial fits' "
                 "(the views alone cannot fix it)")
    # view term: seeded subsample of each frame's valid static pixels
    rng = np.random.default_rng(seed)
    picks = []
    for k in range(len(frames)):
        idx = np.flatnonzero(V[k].reshape(-1))
        if len(idx) > MAX_PIXELS:
            idx = np.sort(rng.choice(idx, MAX_PIXELS, replace=False))
        picks.append(idx)
    width = max([len(p) for p in picks] + [1])
    pix = np.zeros((len(frames), width), np.int64)
    pix_ok = np.zeros((len(frames), width), np.float32)
    for k, idx in enumerate(picks):
        pix[k, :len(idx)], pix_ok[k, :len(idx)] = idx, 1.0
    pairs = _pairs(frames, window)
    ei = T([index[i] for i, _ in pairs], torch.long)
    ej = T([index[j] for _, j in pairs], torch.long)
    pix_t, pix_ok_t = T(pix, torch.long), T(pix_ok)
    stride_x = float(cols[1] - cols[0]) if w > 1 else 1.0
    stride_y = float(rows[1] - rows[0]) if h > 1 else 1.0
    a = torch.zeros(len(frames), device=device, requires_grad=True)
    b = torch.zeros(len(frames), device=device, requires_grad=True)

    def inverse_maps() -> torch.Tensor:
        return torch.exp(a)[:, None, None] * (s0[:, None, None] * Dt + o0[:, None, None]) + (b * m)[:, None, None]

    def residuals() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(anchor residuals [A], view residuals [E, Q], their weights [E, Q])."""
        u = inverse_maps()  # [F, h, w]
        ua = torch.exp(a[fa]) * (s0[fa] * da + o0[fa]) + b[fa] * m[fa]
        r_anchor = ua * za - 1.0
        if not pairs:
            return r_anchor, u.new_zeros(0, 1), u.new_zeros(0, 1)
        flat = u.reshape(len(frames), -1)
        src = pix_t[ei]  # [E, Q]
        ui = torch.gather(flat[ei], 1, src).clamp_min(1e-12)
        X = torch.gather(rays[ei], 1, src[..., None].expand(-1, -1, 3)) / ui[..., None]  # camera i
        world = torch.einsum("eji,eqj->eqi", R[ei], X - t[ei][:, None])  # R_i^T (X - t_i)
        Y = torch.einsum("eij,eqj->eqi", R[ej], world) + t[ej][:, None]
        z = Y[..., 2]
        zs = torch.where(z > 1e-9, z, torch.ones_like(z))
        px = Kt[ej][:, 0, 0, None] * Y[..., 0] / zs + Kt[ej][:, 0, 2, None]
        py = Kt[ej][:, 1, 1, None] * Y[..., 1] / zs + Kt[ej][:, 1, 2, None]
        gx = (px - 0.5 - float(cols[0])) / stride_x / max(w - 1, 1) * 2 - 1
        gy = (py - 0.5 - float(rows[0])) / stride_y / max(h - 1, 1) * 2 - 1
        grid = torch.stack([gx, gy], -1)[:, :, None]  # [E, Q, 1, 2]
        uj = F.grid_sample(u[ej][:, None], grid, align_corners=True).reshape(len(pairs), -1)
        ok = F.grid_sample(Vt[ej][:, None], grid, align_corners=True).reshape(len(pairs), -1)
        inside = (gx.abs() <= 1) & (gy.abs() <= 1) & (z > 1e-9)
        weight = pix_ok_t[ei] * inside * (ok > 0.999)
        return r_anchor, torch.where(weight > 0, uj * z - 1.0, torch.zeros_like(z)), weight.detach()

    def loss_fn() -> torch.Tensor:
        r_anchor, r_view, weight = residuals()
        total = r_anchor.new_zeros(())
        if len(r_anchor):
            total = total + (va * _rho(r_anchor)).sum() / va.sum().clamp_min(1e-12)
        else:  # gauge: the frames' mean log scale stays at the initial fits'
            ratio = (torch.exp(a) + b).clamp_min(1e-6)
            total = total + SCALE_WEIGHT * torch.log(ratio).mean() ** 2
        if weight.sum() > 0:
            total = total + VIEW_WEIGHT * (weight * _rho(r_view)).sum() / weight.sum()
        return total

    def medians() -> dict:
        with torch.no_grad():
            r_anchor, r_view, weight = residuals()
        view = r_view[weight > 0].abs()
        return {"anchors": float(r_anchor.abs().median()) if len(r_anchor) else None,
                "views": float(view.median()) if len(view) else None}

    before = medians()
    optimizer = torch.optim.Adam([a, b], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, max(iterations, 1), eta_min=lr * 0.01)
    bar = tqdm(range(iterations), desc="align (inverse depth)", disable=not progress, leave=False,
               mininterval=0.1 if sys.stderr.isatty() else 30.0)
    for _ in bar:
        optimizer.zero_grad()
        loss = loss_fn()
        if not loss.requires_grad:
            break
        loss.backward()
        optimizer.step()
        schedule.step()
    after = medians()
    scale = (torch.exp(a) * s0).detach().cpu().double().numpy()
    shift = (torch.exp(a) * o0 + b * m).detach().cpu().double().numpy()
    states, kept = {}, []
    for k, n in enumerate(frames):
        refined = FrameFit(float(scale[k]), float(shift[k]), fits[n].source)
        u = refined.inverse(D[k][V[k]]) if V[k].any() else np.ones(1)
        if not (np.isfinite(scale[k]) and np.isfinite(shift[k])) or float((u <= 0).mean()) > MAX_BEHIND:
            refined = fits[n]
            kept.append(provider.cameras[n].image_name)
        states[n] = FrameState(refined.scale, refined.shift, provider.viewmats[n], fits[n].source != "none",
                               inverse=True, max_depth=max_depth[k])
    report = {"mode": "inverse depth (anchored)", "frames": len(frames), "edges": len(pairs),
              "anchors": int(len(fa)), "scale_anchor": scale_anchor, "iterations": iterations,
              "residual_init": before, "residual": after, "kept_initial_fit": kept,
              "seconds": time.perf_counter() - start}
    return states, report


__all__ = ["align_inverse"]
