"""Monocular disparity at the scene's scale: a robust per-frame affine fit in INVERSE depth.

    fit = fit_disparity(d, z)                         # 1 / z ~ fit.scale * d + fit.shift, or None
    fits = fit_frames(cameras, points, masks)         # one FrameFit per camera (with fallbacks)
    z = fits[n].depth(disparity)                      # [H, W] metric z-depth, NaN where unusable

Real datasets ship disparity from a monocular network (NVIDIA's `disp/*.npy`: MiDaS): inverse
depth up to an unknown per-frame scale AND shift, 1 / z = s_n d_n + o_n. With the dataset's
cameras fixed, the scene already has a metric scale; each frame's (s_n, o_n) is fitted to it:

1. sparse points: the host's triangulated/dataset points that project into frame n (in front,
   inside the image, outside its motion mask) give pairs (d_k, z_k). The fit minimises the
   RELATIVE residual r_k = (s d_k + o) z_k - 1 (~ the relative depth error; linear in s, o):
   least-median-of-squares over seeded 2-point samples, then Tukey biweight IRLS with the scale
   fixed at the start's robust scale, kept unless it worsens the median |residual| by more than
   10% (a coherent cluster of wrong points must not pull the polish). Every median and the
   polish count each point with its vote, 1 / (points in its cell of a 16-cell grid along the
   image's longer side): one vote per image region, not per point (`coverage_weights`; above
   SCORE_POINTS points the samples' medians are taken on that many points drawn by vote). It is
   accepted with at least MIN_POINTS inliers (|r| < 3 sigma), s > 0, at most MAX_BEHIND of the
   frame's valid pixels with s d + o <= 0 (behind the camera / at infinity), and, when the
   dataset has near/far bounds, the frame's median fitted depth inside
   [near / BOUNDS_SLACK, far * BOUNDS_SLACK]. Its report: `residual` (median |r| of the
   inliers), `residual_all` (of every point), both in sample, and `held_out` (fit_frames: the
   vote-weighted median |r| of every point under the fit to the other half of the image's
   regions, `held_out_residual`: what the prior's error is on points the fit did not see).
2. bounds (fallback): the frame's disparity percentiles [2%, 98%] mapped to [1 / far, 1 / near]
   (`poses_bounds.npy` near/far: the depth range of that frame's points).
3. neighbour (fallback): the nearest frame in time with a sparse fit lends its depth range: the
   frame's [10%, 90%] disparity percentiles map to the inverse depths the neighbour's fit gives
   its own percentiles (consecutive frames see similar depths).
4. none: no metric evidence at all (FrameFit.source "none", depth() is all NaN).

Everything here is numpy on the CPU; the global refinement is canonical/inverse.py.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

MIN_POINTS = 8  # inliers a sparse fit needs
MAX_BEHIND = 0.05  # largest fraction of a frame's pixels a fit may put behind the camera / at infinity
BOUNDS_SLACK = 2.0  # a fit's median depth must lie in [near / slack, far * slack]
TUKEY = 4.685  # biweight cut-off in robust sigmas (95% efficiency under Gaussian noise)
MAX_POLISH_LOSS = 1.1  # the IRLS polish is kept when its median |residual| is at most this x the start's
COVERAGE_CELLS = 16  # one vote per cell of a grid with this many cells along the image's longer side
SAMPLES = 200  # 2-point samples of the least-median-of-squares start
SCORE_POINTS = 2048  # above this many points, each sample's median is taken on this many drawn by vote
HELD_OUT_MIN = 30  # pairs each half needs for a held-out residual
REGION_BLOCKS = 4  # held-out folds: a checkerboard with this many squares along the longer side
FLAT_DISPARITY = 1e-6  # disparity spread (relative to its largest magnitude) below which a map is flat


def project(points: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pixel x [P], pixel y [P], depth z [P]) of world points [P, 3] in `camera` (z <= 0: behind)."""
    viewmat = camera.viewmat.detach().cpu().double().numpy()
    K = camera.K.detach().cpu().double().numpy()
    cam = np.asarray(points, np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    safe = np.where(np.abs(z) > 1e-9, z, 1e-9)
    return K[0, 0] * cam[:, 0] / safe + K[0, 2], K[1, 1] * cam[:, 1] / safe + K[1, 2], z


@dataclass
class FrameFit:
    """1 / z = scale * d + shift for one frame. source: sparse | bounds | neighbour | none."""

    scale: float
    shift: float
    source: str
    points: int = 0  # sparse points that projected into the frame
    inliers: int = 0
    residual: float | None = None  # median |relative residual| of the inliers (in sample)
    residual_all: float | None = None  # median |relative residual| of every point (in sample)
    held_out: float | None = None  # out of sample: fit_frames' held_out_residual (None: not measured)
    rejected: list[str] = field(default_factory=list)  # why better sources were not used

    @property
    def usable(self) -> bool:
        return self.source != "none"

    def inverse(self, disparity: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(disparity, np.float64) + self.shift

    def depth(self, disparity: np.ndarray, max_depth: float = np.inf) -> np.ndarray:
        """Metric z-depth of `disparity` (any shape); NaN where s d + o <= 0 or beyond max_depth."""
        if not self.usable:
            return np.full(np.shape(disparity), np.nan)
        u = self.inverse(disparity)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(u > 0, 1.0 / u, np.nan)
        return np.where(z <= max_depth, z, np.nan)

    def as_dict(self) -> dict:
        return {"scale": self.scale, "shift": self.shift, "source": self.source, "points": self.points,
                "inliers": self.inliers, "residual": self.residual, "residual_all": self.residual_all,
                "held_out": self.held_out, "rejected": self.rejected}


def coverage_weights(x: np.ndarray, y: np.ndarray, width: int, height: int,
                     cells: int = COVERAGE_CELLS) -> np.ndarray:
    """[K] weights of pixels (x, y) [K]: 1 / (points in the same image cell), so every covered cell
    of a grid with `cells` cells along the longer side has one vote in total.

    Triangulated points crowd on textured surfaces; a textured moving object triangulated as if
    static (moving along the rig's baseline, where the epipolar geometry cannot tell) can hold a
    quarter of a frame's points on a sixth of its image and, being self-consistent while the
    static points carry the network's few-percent error, win a median over points.
    """
    size = max(width, height) / max(cells, 1)
    col = np.floor(np.asarray(x, np.float64) / size).astype(np.int64)
    row = np.floor(np.asarray(y, np.float64) / size).astype(np.int64)
    if not len(col):
        return np.zeros(0)
    _, group, counts = np.unique(np.stack([row, col], 1), axis=0, return_inverse=True, return_counts=True)
    return 1.0 / counts[group.reshape(-1)]


def weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted median along the last axis of `values` [..., K] with weights [K] (> 0)."""
    order = np.argsort(values, axis=-1)
    ordered = np.take_along_axis(values, order, -1)
    cumulative = np.cumsum(np.asarray(weights, np.float64)[order], -1)
    below = (cumulative < 0.5 * cumulative[..., -1:]).sum(-1)
    return np.take_along_axis(ordered, np.minimum(below, values.shape[-1] - 1)[..., None], -1)[..., 0]


def tukey_weights(residuals: np.ndarray, sigma: float) -> np.ndarray:
    """Tukey biweight [K] of residuals [K] at robust scale `sigma` (0 beyond TUKEY sigmas)."""
    u = np.asarray(residuals) / (TUKEY * max(sigma, 1e-3))
    return np.where(np.abs(u) < 1.0, (1.0 - u ** 2) ** 2, 0.0)


def _residual(d: np.ndarray, z: np.ndarray, s: float, o: float) -> np.ndarray:
    return (s * d + o) * z - 1.0


def _weighted_solve(d: np.ndarray, z: np.ndarray, w: np.ndarray) -> tuple[float, float] | None:
    A = np.stack([d * z, z], 1) * np.sqrt(w)[:, None]
    b = np.sqrt(w)
    try:
        (s, o), *_ = np.linalg.lstsq(A, b, rcond=None)
    except np.linalg.LinAlgError:
        return None
    return (float(s), float(o)) if np.isfinite(s) and np.isfinite(o) else None


def fit_disparity(disparity: np.ndarray, depth: np.ndarray, iterations: int = 10,
                  seed: int = 0, weights: np.ndarray | None = None) -> FrameFit | None:
    """Robust (s, o) with 1 / depth ~ s * disparity + o from pairs [K] (see the module docstring).

    weights: [K] votes of the pairs (coverage_weights; None: one each) in the medians and the polish.
    Returns None with fewer than MIN_POINTS usable pairs, a flat disparity at the pairs (spread at
    most FLAT_DISPARITY of its magnitude: the scale is not determined), no positive-scale solution
    or fewer than MIN_POINTS inliers. The FrameFit's source is "sparse".
    """
    d, z = np.asarray(disparity, np.float64).ravel(), np.asarray(depth, np.float64).ravel()
    votes = np.ones(len(d)) if weights is None else np.asarray(weights, np.float64).ravel()
    ok = np.isfinite(d) & np.isfinite(z) & (z > 0) & (votes > 0)
    d, z, votes = d[ok], z[ok], votes[ok]
    if len(d) < MIN_POINTS:
        return None
    if np.ptp(d) <= FLAT_DISPARITY * max(float(np.abs(d).max()), 1e-30):
        return None  # a flat map: every scale fits as well (least squares would return an arbitrary one)
    rng = np.random.default_rng(seed)
    # least median of squares over 2-point samples (drawn by vote: every region as likely), vectorised
    a, b = rng.choice(len(d), (2, SAMPLES), p=votes / votes.sum())
    a, b = a[a != b], b[a != b]
    det = d[a] * z[a] * z[b] - z[a] * d[b] * z[b]
    good = np.abs(det) > 1e-12 * z[a] * z[b] * (np.abs(d[a]) + np.abs(d[b]) + 1e-30)
    det = np.where(good, det, 1.0)
    s_all, o_all = (z[b] - z[a]) / det, (d[a] * z[a] - d[b] * z[b]) / det
    good &= s_all > 0
    best = None
    if good.any():
        s_all, o_all = s_all[good], o_all[good]
        if len(d) <= SCORE_POINTS:  # each candidate's weighted median residual
            cost = weighted_median(np.abs((s_all[:, None] * d[None] + o_all[:, None]) * z[None] - 1.0), votes)
        else:  # ... estimated on points drawn by vote (a frame with 20k points: 20 ms, not 0.4 s)
            score = rng.choice(len(d), SCORE_POINTS, p=votes / votes.sum())
            cost = np.median(np.abs((s_all[:, None] * d[score][None] + o_all[:, None]) * z[score][None] - 1.0), axis=1)
        k = int(np.argmin(cost))
        best = (float(s_all[k]), float(o_all[k]))
    if best is None:
        best = _weighted_solve(d, z, votes)
        if best is None or not best[0] > 0:
            return None
    s, o = best
    start_cost = float(weighted_median(np.abs(_residual(d, z, s, o)), votes))
    # Scale fixed at the robust start's (Rousseeuw's LMedS scale): re-estimating it from every
    # residual each step lets a coherent cluster of wrong points (a moving object triangulated along
    # the rig's baseline: a quarter of the points, all 1.5x too far) widen it, join the fit and pull
    # the map to a compromise that fits neither (real-priors truck: median |r| 0.048 -> 0.096).
    sigma = 1.4826 * (1.0 + 5.0 / max(len(d) - 2, 1)) * start_cost + 1e-9
    refined = (s, o)
    for _ in range(iterations):  # Tukey biweight IRLS (redescending: far points get no weight)
        w = tukey_weights(_residual(d, z, *refined), sigma) * votes
        if (w > 0).sum() < MIN_POINTS:
            break
        solved = _weighted_solve(d, z, w)
        if solved is None:
            break
        refined = solved
    # The polish must not undo the robust start: kept unless it worsens the median residual.
    polished_cost = float(weighted_median(np.abs(_residual(d, z, *refined)), votes))
    if refined[0] > 0 and polished_cost <= MAX_POLISH_LOSS * start_cost:
        s, o = refined
    if not s > 0:
        return None
    r = _residual(d, z, s, o)
    sigma = 1.4826 * float(weighted_median(np.abs(r), votes)) + 1e-9
    inliers = np.abs(r) <= 3.0 * max(sigma, 1e-3)
    if inliers.sum() < MIN_POINTS:
        return None
    return FrameFit(s, o, "sparse", points=len(d), inliers=int(inliers.sum()),
                    residual=float(np.median(np.abs(r[inliers]))), residual_all=float(np.median(np.abs(r))))


def region_folds(x: np.ndarray, y: np.ndarray, width: int, height: int, blocks: int = REGION_BLOCKS) -> np.ndarray:
    """[K] bool: True for pixels (x, y) [K] on the "black" squares of a checkerboard with `blocks`
    squares along the image's longer side. Held-out points by image region: a point is never
    judged by a fit to its immediate neighbours (random halves put a training point next to
    almost every held-out one), while each half still spans the whole image and its depth range."""
    size = max(width, height) / max(blocks, 1)
    col = np.floor(np.asarray(x, np.float64) / size).astype(np.int64)
    row = np.floor(np.asarray(y, np.float64) / size).astype(np.int64)
    return (row + col) % 2 == 0


def held_out_residual(d: np.ndarray, z: np.ndarray, x: np.ndarray, y: np.ndarray, width: int,
                      height: int) -> float | None:
    """Vote-weighted median |relative residual| of every sparse pair [K] under the affine fit to
    the OTHER half (region_folds), both halves in turn; None when a half has fewer than
    HELD_OUT_MIN pairs (a fit to 15 points of a real-priors frame was off by 10x in scale: the
    figure would measure the small sample, not the prior) or no fit."""
    fold = region_folds(x, y, width, height)
    if min(int(fold.sum()), int((~fold).sum())) < HELD_OUT_MIN:
        return None
    votes = coverage_weights(x, y, width, height)
    held, weights = [], []
    for train in (fold, ~fold):
        fit = fit_disparity(d[train], z[train], weights=votes[train])
        if fit is None or not (~train).any():
            return None
        held.append(np.abs(_residual(d[~train], z[~train], fit.scale, fit.shift)))
        weights.append(votes[~train])
    return float(weighted_median(np.concatenate(held), np.concatenate(weights)))


def _valid_disparity(disparity: np.ndarray) -> np.ndarray:
    d = np.asarray(disparity, np.float64)
    return d[np.isfinite(d)]


def bounds_fit(disparity: np.ndarray, near: float, far: float) -> FrameFit | None:
    """Disparity percentiles [2, 98] mapped to [1 / far, 1 / near] (None for a flat disparity)."""
    d = _valid_disparity(disparity)
    if len(d) < 2 or not 0 < near < far:
        return None
    lo, hi = np.percentile(d, [2, 98])
    if not hi > lo:
        return None
    s = (1.0 / near - 1.0 / far) / (hi - lo)
    return FrameFit(float(s), float(1.0 / far - s * lo), "bounds")


def neighbour_fit(disparity: np.ndarray, other: FrameFit, other_disparity: np.ndarray) -> FrameFit | None:
    """The frame's [10, 90] disparity percentiles mapped to what `other`'s fit gives its own."""
    d, e = _valid_disparity(disparity), _valid_disparity(other_disparity)
    if len(d) < 2 or len(e) < 2:
        return None
    lo, hi = np.percentile(d, [10, 90])
    u_lo, u_hi = other.inverse(np.percentile(e, [10, 90]))
    if not (hi > lo and u_hi > u_lo > 0):
        return None
    s = (u_hi - u_lo) / (hi - lo)
    return FrameFit(float(s), float(u_lo - s * lo), "neighbour")


def _check(fit: FrameFit, disparity: np.ndarray, bounds: tuple[float, float] | None) -> str | None:
    """Why a sparse fit is not acceptable for its frame, or None."""
    d = _valid_disparity(disparity)
    u = fit.inverse(d)
    behind = float((u <= 0).mean()) if len(u) else 1.0
    if behind > MAX_BEHIND:
        return f"puts {behind:.0%} of the pixels behind the camera or at infinity"
    if bounds is not None:
        median = float(np.median(1.0 / u[u > 0]))
        near, far = bounds
        if not near / BOUNDS_SLACK <= median <= far * BOUNDS_SLACK:
            return f"median depth {median:.4g} outside the bounds [{near:.4g}, {far:.4g}]"
    return None


def sparse_pairs(camera, disparity: np.ndarray, points: np.ndarray,
                 mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(disparity [K], depth [K]) at the static points that project into `camera` (nearest pixel)."""
    d, z, _ = sparse_votes(camera, disparity, points, mask)
    return d, z


def sparse_votes(camera, disparity: np.ndarray, points: np.ndarray,
                 mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sparse_pairs plus each pair's vote [K] (coverage_weights of its pixel)."""
    d, z, votes, _, _ = sparse_pixels(camera, disparity, points, mask)
    return d, z, votes


def sparse_pixels(camera, disparity: np.ndarray, points: np.ndarray, mask: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """sparse_votes plus each pair's pixel coordinates x [K], y [K]."""
    if len(points) == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
    x, y, z = project(points, camera)
    col, row = np.floor(x).astype(int), np.floor(y).astype(int)
    h, w = np.shape(disparity)
    seen = (z > 1e-9) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    if mask is not None:
        seen[seen] &= ~np.asarray(mask, bool)[row[seen], col[seen]]
    votes = coverage_weights(x[seen], y[seen], w, h)
    return np.asarray(disparity, np.float64)[row[seen], col[seen]], z[seen], votes, x[seen], y[seen]


def camera_bounds(camera) -> tuple[float, float] | None:
    """(near, far) of a camera from the dataset (extras["near_far"]), or None."""
    near_far = camera.extras.get("near_far") if getattr(camera, "extras", None) else None
    if near_far is None:
        return None
    near, far = (float(v) for v in np.asarray(near_far.detach().cpu() if hasattr(near_far, "detach") else near_far)[:2])
    return (near, far) if 0 < near < far else None


def fit_frames(cameras: Sequence, disparities: Sequence[np.ndarray], points: np.ndarray | None,
               masks: Sequence[np.ndarray] | None = None, use_bounds: bool = True) -> list[FrameFit]:
    """One FrameFit per camera: sparse, else bounds, else neighbour, else none (module docstring).

    cameras: with K, viewmat (and extras["near_far"]); disparities: [H, W] per camera, the
    camera's resolution; points: [P, 3] metric static points (or None); masks: [H, W] bool.
    """
    points = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    fits: list[FrameFit | None] = []
    reasons: list[list[str]] = []
    counts: list[int] = []
    for k, (cam, disparity) in enumerate(zip(cameras, disparities)):
        bounds = camera_bounds(cam) if use_bounds else None
        d, z, votes, x, y = sparse_pixels(cam, disparity, points, None if masks is None else masks[k])
        fit = fit_disparity(d, z, weights=votes) if len(d) else None
        if fit is not None:
            fit.held_out = held_out_residual(d, z, x, y, *np.shape(disparity)[::-1])
        counts.append(len(d))
        why = [f"{len(d)} sparse points" if fit is None else None]
        if fit is not None:
            problem = _check(fit, disparity, bounds)
            if problem:
                why, fit = [f"sparse fit {problem}"], None
        if fit is None and bounds is not None:
            fit = bounds_fit(disparity, *bounds)
        fits.append(fit)
        reasons.append([w for w in why if w])
    order = sorted(range(len(cameras)), key=lambda k: (cameras[k].time, cameras[k].frame_index))
    sparse = [k for k in order if fits[k] is not None and fits[k].source == "sparse"]
    out = []
    for k in range(len(cameras)):
        fit = fits[k]
        if fit is None and sparse:
            near = min(sparse, key=lambda m: abs(order.index(m) - order.index(k)))
            fit = neighbour_fit(disparities[k], fits[near], disparities[near])
        if fit is None:
            fit = FrameFit(float("nan"), float("nan"), "none")
        fit.points = counts[k]
        fit.rejected = reasons[k] if fit.source != "sparse" else []
        out.append(fit)
    return out


def summary(fits: Sequence[FrameFit]) -> dict:
    """{source: count} plus the medians over the sparse fits of their residuals (for reports):
    median_residual (inliers, in sample), median_residual_all (every point, in sample) and
    median_held_out (out of sample, fit_frames' held_out_residual; the one the check gates on)."""
    counts: dict[str, int] = {}
    for fit in fits:
        counts[fit.source] = counts.get(fit.source, 0) + 1

    def median(name: str) -> float | None:
        values = [getattr(f, name) for f in fits if getattr(f, name) is not None]
        return float(np.median(values)) if values else None

    return {"sources": counts, "median_residual": median("residual"), "median_residual_all": median("residual_all"),
            "median_held_out": median("held_out")}


__all__ = ["BOUNDS_SLACK", "FrameFit", "MAX_BEHIND", "MIN_POINTS", "bounds_fit", "camera_bounds", "coverage_weights",
           "fit_disparity", "fit_frames", "held_out_residual", "neighbour_fit", "project", "region_folds",
           "sparse_pairs", "sparse_pixels", "sparse_votes", "summary",
           "tukey_weights", "weighted_median"]
