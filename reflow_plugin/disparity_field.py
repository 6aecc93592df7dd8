"""A smooth per-frame correction of monocular disparity, fitted to the sparse static points.

    corrected, report = correct_disparity(camera, disparity, points, grid=4)   # [H, W], dict

A monocular network's disparity is inverse depth up to a per-frame affine map AND a smooth,
low-frequency error (a ramp over the floor, a wall a few percent too near); the affine fit of
reflow_plugin.disparity removes the first and leaves the second, which places the static cloud a
few percent off and, worse, makes the estimated motion masks' re-projection test see motion
everywhere the error changes between frames (docs/REAL_PRIORS.md, "What the monocular depth's errors cost":
on the real-priors truck the 5% error alone takes the masks' IoU from 0.85 to 0.23). Model:

    1 / z(p) = (s d(p) + o) exp(g(p))

with (s, o) the robust affine fit and g a bilinear field on a G x G grid of control values over
the image. g is fitted to the log residuals r_k = log((1 / z_k) / (s d_k + o)) of the affine fit's
inlier points (those beyond 3 robust sigmas of the median left out) by regularised, weighted least
squares, iterated as a Tukey biweight:

    min_c  sum_k w_k (B_k c - r_k)^2 / sum_k w_k + SMOOTH ||D c||^2 + SHRINK ||c||^2

(B_k: the bilinear weights of point k's pixel, D: differences of neighbouring control values,
w_k = v_k tukey((B_k c - r_k) / (4.685 sigma)), v_k the point's coverage vote: one vote per image
region, reflow_plugin.disparity.coverage_weights). sigma starts as the robust spread of the affine
fit's residuals and is re-estimated after each of the first RESCALE_PASSES solves as the robust
spread of what the field leaves (1.4826 x the vote-weighted median |B_k c - r_k|, at least
SIGMA_FLOOR), then held. Why: the affine residuals' spread contains the very error the field
explains (5% on the real-priors scenes) AND the moving object's points, so a biweight at that
scale still trusted the near tail of a moving object triangulated as if static (a compact,
textured, self-consistent cluster 1.4-1.7x too far on the real-priors truck: 6-46 of its ~200
points per frame inside 3 sigmas), and the field bent the truck up to 13% farther (moving-pixel depth error
0.054 with the affine fit alone, 0.109 corrected; with the re-estimated scale 0.056). Where no
static point exists (behind a large moving object) the field is an interpolation of its
surroundings and can still be a few percent off there.
It is kept only if it lowers the median |residual| on points it was NOT fitted to by at least
MIN_GAIN of it and MIN_ABS_GAIN. Out of sample throughout: the points are split by image region
(reflow_plugin.disparity.region_folds: a checkerboard of 4 squares along the longer side), and
for each half the affine fit, its inlier gate and the field are fitted on the other half alone;
the held-out median is vote-weighted like the fit and taken over every held-out point (the
outliers included: a median over them is robust, and gating before the split would judge the
field only where it already agrees). Kept, it is the one fitted to all points. The corrected disparity is

    d'(p) = ((s d(p) + o) exp(g(p)) - o) / s

so the same affine map gives the corrected inverse depth and every later step (masks, canonical
space, seeds, the anchored alignment) reads d' as it read d. Pixels where s d + o <= 0 (no depth)
are left as they are. A frame with fewer than MIN_PER_CONTROL x G^2 inliers is left as it is.
"""
from __future__ import annotations

import numpy as np

from .disparity import coverage_weights, fit_disparity, project, region_folds, tukey_weights, weighted_median

SMOOTH = 1e-3  # weight of the neighbouring-control differences
SHRINK = 1e-5  # weight pulling every control value toward 0 (no correction)
MIN_PER_CONTROL = 4  # inliers needed per control value
MIN_GAIN = 0.1  # the held-out median |residual| must fall by at least this fraction
MIN_ABS_GAIN = 0.002  # ... and by at least this much (0.2% of the depth: below, nothing worth correcting)
RESCALE_PASSES = 2  # solves after which the biweight's scale is re-estimated from what the field leaves
SIGMA_FLOOR = 0.005  # lowest re-estimated scale (0.5% of the depth): points exactly on the field cannot shrink it to 0


def bilinear_weights(x: np.ndarray, y: np.ndarray, width: int, height: int, grid: int) -> np.ndarray:
    """[K, grid * grid] weights of pixel centres (x, y) [K] on a grid of control values spanning the image."""
    gx = np.clip(np.asarray(x, np.float64) / max(width, 1) * (grid - 1), 0, grid - 1)
    gy = np.clip(np.asarray(y, np.float64) / max(height, 1) * (grid - 1), 0, grid - 1)
    x0, y0 = np.minimum(np.floor(gx).astype(int), grid - 2), np.minimum(np.floor(gy).astype(int), grid - 2)
    fx, fy = gx - x0, gy - y0
    weights = np.zeros((len(gx), grid * grid))
    rows = np.arange(len(gx))
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            np.add.at(weights, (rows, (y0 + dy) * grid + x0 + dx), wy * wx)
    return weights


def _differences(grid: int) -> np.ndarray:
    """[E, grid * grid]: one row per pair of horizontally or vertically neighbouring controls."""
    rows = []
    for i in range(grid):
        for j in range(grid):
            for di, dj in ((0, 1), (1, 0)):
                if i + di < grid and j + dj < grid:
                    row = np.zeros(grid * grid)
                    row[i * grid + j], row[(i + di) * grid + j + dj] = -1.0, 1.0
                    rows.append(row)
    return np.asarray(rows)


def fit_field(weights: np.ndarray, residuals: np.ndarray, grid: int, votes: np.ndarray | None = None,
              sigma: float | None = None, iterations: int = 5) -> np.ndarray:
    """[grid * grid] control values minimising the module docstring's regularised least squares,
    each point counted with its vote [K] and, given a robust start scale `sigma`, a Tukey biweight
    whose scale is re-estimated after the first RESCALE_PASSES solves."""
    votes = np.ones(len(residuals)) if votes is None else np.asarray(votes, np.float64)
    D = _differences(grid)
    regulariser = SMOOTH * D.T @ D + SHRINK * np.eye(grid * grid)
    w = votes.copy()
    values = np.zeros(grid * grid)
    for step in range(1 if sigma is None else iterations):
        total = max(float(w.sum()), 1e-12)
        A = (weights * w[:, None]).T @ weights / total + regulariser
        values = np.linalg.solve(A, (weights * w[:, None]).T @ residuals / total)
        if sigma is not None:
            left = residuals - weights @ values
            if step < RESCALE_PASSES:
                sigma = max(1.4826 * float(weighted_median(np.abs(left), votes)), SIGMA_FLOOR)
            w = votes * tukey_weights(left, sigma)
    return values


def field_map(values: np.ndarray, width: int, height: int, grid: int) -> np.ndarray:
    """[height, width] field g at every pixel centre."""
    ys, xs = np.mgrid[0:height, 0:width]
    return (bilinear_weights(xs.ravel() + 0.5, ys.ravel() + 0.5, width, height, grid) @ values).reshape(height, width)


def _inliers(r: np.ndarray, votes: np.ndarray) -> tuple[np.ndarray, float]:
    """(inlier mask [K]: within 3 robust sigmas of the vote-weighted median, that sigma) of log residuals [K]."""
    centre = float(weighted_median(r, votes))
    sigma = 1.4826 * float(weighted_median(np.abs(r - centre), votes)) + 1e-9
    return np.abs(r - centre) <= 3.0 * max(sigma, 1e-3), sigma


def _log_residuals(fit, d: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log residuals r [K] = log((1 / z) / (s d + o)), usable [K]: s d + o > 0) of an affine fit."""
    u = fit.inverse(d)
    ok = (u > 0) & np.isfinite(u)
    return np.log(np.where(ok, 1.0 / (z * np.where(ok, u, 1.0)), 1.0)), ok


def _fit(x: np.ndarray, y: np.ndarray, d: np.ndarray, z: np.ndarray, width: int, height: int, grid: int):
    """(affine fit or None, field values [grid^2] or None, indices of the affine fit's inliers [I])
    of the pairs [K]: the affine fit, then the field on its inliers (None with fewer than
    MIN_PER_CONTROL per control value)."""
    votes = coverage_weights(x, y, width, height)
    fit = fit_disparity(d, z, weights=votes) if len(z) else None
    if fit is None:
        return None, None, np.zeros(0, np.int64)
    r, ok = _log_residuals(fit, d, z)
    if not ok.any():
        return fit, None, np.zeros(0, np.int64)
    inlier, sigma = _inliers(r[ok], votes[ok])
    keep = np.flatnonzero(ok)[inlier]
    if len(keep) < MIN_PER_CONTROL * grid * grid:
        return fit, None, keep
    B = bilinear_weights(x[keep], y[keep], width, height, grid)
    return fit, fit_field(B, r[keep], grid, coverage_weights(x[keep], y[keep], width, height), sigma), keep


def correct_disparity(camera, disparity: np.ndarray, points: np.ndarray, grid: int = 4,
                      mask: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """(corrected disparity [H, W], report) of one frame; the input unchanged when no field is kept.

    camera: with K, viewmat (reflow_plugin.disparity.project); disparity [H, W] at the camera's
    resolution; points [P, 3] metric static points; mask: [H, W] bool pixels to ignore.
    Report: {"corrected": bool, "points": inliers used, "residual": median |relative residual| of
    the affine fit's inliers (in sample), "held_out_before" / "held_out_after": the vote-weighted
    median |relative residual| of every point of one half of the image's regions under the affine
    fit / affine fit + field fitted to the other half (both halves in turn), "residual_corrected":
    the in-sample inlier median after the correction (when kept), "why": reason when not kept}.
    """
    disparity = np.asarray(disparity, np.float64)
    height, width = disparity.shape
    x, y, z = _pixels(camera, points, width, height, mask)
    d = disparity[np.floor(y).astype(int), np.floor(x).astype(int)] if len(z) else np.zeros(0)
    fit, values, inlier = _fit(x, y, d, z, width, height, grid)
    if fit is None:
        return disparity, {"corrected": False, "points": int(len(z)), "why": "no affine fit"}
    r, _ = _log_residuals(fit, d, z)
    report = {"corrected": False, "points": len(inlier), "residual": float(np.median(np.abs(np.expm1(r[inlier]))))
              if len(inlier) else None}
    if values is None:
        return disparity, dict(report, why=f"{len(inlier)} inliers (need {MIN_PER_CONTROL * grid * grid})")
    # out of sample: each half of the image's regions judged by the fits to the other half
    fold = region_folds(x, y, width, height)
    votes = coverage_weights(x, y, width, height)
    before, after, weights = [], [], []
    for train in (fold, ~fold):
        held = ~train
        fold_fit, fold_values, _ = _fit(x[train], y[train], d[train], z[train], width, height, grid)
        if fold_fit is None or fold_values is None or not held.any():
            return disparity, dict(report, why="too few points in one half of the image's regions")
        r_held, ok_held = _log_residuals(fold_fit, d[held], z[held])
        field = bilinear_weights(x[held], y[held], width, height, grid) @ fold_values
        # |z u - 1| (reflow_plugin.disparity's relative residual), u the inverse depth read at the point
        before.append(np.where(ok_held, np.abs(np.expm1(-r_held)), 1.0))  # no depth: a 100% error
        after.append(np.where(ok_held, np.abs(np.expm1(field - r_held)), 1.0))
        weights.append(votes[held])
    weights = np.concatenate(weights)
    held_before = float(weighted_median(np.concatenate(before), weights))
    held_after = float(weighted_median(np.concatenate(after), weights))
    report.update(held_out_before=held_before, held_out_after=held_after)
    if not (held_after <= (1.0 - MIN_GAIN) * held_before and held_before - held_after >= MIN_ABS_GAIN):
        return disparity, dict(report, why="no held-out gain")
    g = field_map(values, width, height, grid)
    full = fit.inverse(disparity)
    corrected = np.where(full > 0, (full * np.exp(g) - fit.shift) / fit.scale, disparity)
    B = bilinear_weights(x[inlier], y[inlier], width, height, grid)
    report.update(corrected=True, residual_corrected=float(np.median(np.abs(np.expm1(r[inlier] - B @ values)))),
                  field_range=[float(values.min()), float(values.max())])
    return corrected, report


def _pixels(camera, points: np.ndarray, width: int, height: int,
            mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (x, y) [K] and depths z [K] of the points that project into the frame."""
    if len(points) == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    x, y, z = project(np.asarray(points, np.float64), camera)
    col, row = np.floor(x).astype(int), np.floor(y).astype(int)
    seen = (z > 1e-9) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    if mask is not None:
        seen[seen] &= ~np.asarray(mask, bool)[row[seen], col[seen]]
    return x[seen], y[seen], z[seen]


__all__ = ["bilinear_weights", "correct_disparity", "field_map", "fit_field"]
