"""Is an initial cloud at the scene's scale? Checked before training, like the host checks a dataset cloud.

    result = check_initial_cloud(static_points, dynamic_groups, cameras, anchors)
    result.passed, result.failure, result.measurements

A canonical cloud built from monocular disparity at the wrong scale still lies inside every view
(each frame back-projects its own pixels), so coverage alone does not catch it. Three measurements:

- views: the fraction of training views that see a static point (the host's
  `check_cloud_against_cameras`); at least MIN_VIEWS ("most training views").
- depth: where the host's sparse points (`anchors`) fall on a cell (CELL_PX pixels) that the static
  cloud covers, the ratio of the cloud's nearest depth in that cell to the sparse point's depth;
  the median over every sampled view must lie in DEPTH_RATIO. Without sparse points: the fraction
  of the static points whose depth lies inside the dataset's [near / 2, 2 far] bounds in the views
  that see them, at least MIN_IN_BOUNDS.
- dynamic spread: per group (one keyframe's seeds, or the reference frame's cloud), the RMS
  distance of its points to their centroid x sqrt(2), divided by the radius the group's mask would
  have in the world at the static scene's depth there (sqrt(mask pixels / pi) x depth / focal;
  depth: the sparse points' median in that view, else the bounds' geometric mean, else the static
  cloud's). A flat disc at that depth gives 1; the median over groups must reach MIN_SPREAD. All
  points at one position (seen on a real capture) give 0.

And, on the monocular-disparity path with sparse points, the depth prior's accuracy OUT OF
SAMPLE (`prior_residual`): the median over frames of each frame's held-out residual must stay at
or below `max_fit_residual` (0 = not checked; frames with fewer than 2 x 30 sparse points have no
held-out residual, and where no frame has one the all-point median in sample stands in, named
so). A frame's held-out residual is the vote-weighted median |relative residual| of every sparse
point under the fits to the other half of the image's regions: the affine fit's
(reflow_plugin.disparity.held_out_residual), or, where the smooth correction was kept, the
affine fit + field's (reflow_plugin.disparity_field: 16 values per frame
fitted to the same points, so the corrected disparity's in-sample residual says little). Beside
it the in-sample medians are reported: `fit_residual_inliers` (the inliers of each fit, what
the gate read up to commit 9095855) and `fit_residual_all` (every point). A network's depth that
disagrees that much with the triangulated points after the best per-frame affine map (a real
NVIDIA capture: 14% in sample; the simulator's real-priors scenes: 2.6-3.7% in sample) gives a
dense cloud less accurate than the sparse points it was fitted to.

And, with sparse points, the cloud's accuracy where they can judge it: per sparse point a view
sees on a covered cell, |median cloud depth in the cell / the point's depth - 1|; its median must
stay at or below `max_depth_error` (0 = not checked). This one is IN SAMPLE: the cloud's depth was
fitted to the same points, so it is a lower bound of the cloud's error (the fit's own held-out
residual above is the out-of-sample measure of the same prior). Measured: 0.8% on NVIDIA
Balloon1 through prepare and 3.1-4.6% on the real-priors scenes (comp_init helps on all of them), 7.8% on DAVIS
lady-running (flow provider) and 14% on Balloon1's monocular disparity (comp_init cost the
background on both: docs/REAL_CAPTURES.md).

Views are evenly subsampled (MAX_VIEWS) and clouds randomly (MAX_POINTS, seeded): a check costs
well under a second.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from baselines.data.cloud_check import check_cloud_against_cameras

from ..disparity import camera_bounds, project

MIN_VIEWS = 0.8
DEPTH_RATIO = (0.7, 1.4)
MIN_IN_BOUNDS = 0.8
MIN_SPREAD = 0.1
CELL_PX = 4
MAX_VIEWS = 16
MAX_POINTS = 50_000


@dataclass
class DynamicGroup:
    """Dynamic points [P, 3] seeded from `camera`'s mask [H, W] bool."""

    camera: object
    mask: np.ndarray
    points: np.ndarray


@dataclass
class CloudCheck:
    """passed; failure: one sentence naming the failing measurement (None when passed)."""

    passed: bool
    failure: str | None
    measurements: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"passed": self.passed, "failure": self.failure, **self.measurements}


def _subsample(points: np.ndarray, limit: int, seed: int = 0) -> np.ndarray:
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) > limit:
        points = points[np.random.default_rng(seed).choice(len(points), limit, replace=False)]
    return points


def _views(cameras: Sequence) -> list:
    cameras = list(cameras)
    if len(cameras) <= MAX_VIEWS:
        return cameras
    return [cameras[i] for i in np.linspace(0, len(cameras) - 1, MAX_VIEWS).round().astype(int)]


def _cells(camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(flat cell index [P], depth [P]) of the points inside `camera` (cells of CELL_PX pixels)."""
    x, y, z = project(points, camera)
    cols, rows = -(-camera.width // CELL_PX), -(-camera.height // CELL_PX)
    cx, cy = np.floor(x / CELL_PX).astype(int), np.floor(y / CELL_PX).astype(int)
    inside = (z > 1e-9) & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
    return (cy * cols + cx)[inside], z[inside]


def depth_ratio_to_anchors(static: np.ndarray, anchors: np.ndarray, cameras: Sequence) -> tuple[float | None, int]:
    """(median of cloud depth / sparse-point depth over covered cells, number of comparisons)."""
    ratios = []
    for cam in _views(cameras):
        cells, z = _cells(cam, static)
        if not len(cells):
            continue
        size = (-(-cam.width // CELL_PX)) * (-(-cam.height // CELL_PX))
        nearest = np.full(size, np.inf)
        np.minimum.at(nearest, cells, z)
        a_cells, a_z = _cells(cam, anchors)
        covered = np.isfinite(nearest[a_cells])
        ratios.append(nearest[a_cells[covered]] / a_z[covered])
    ratios = np.concatenate(ratios) if ratios else np.zeros(0)
    return (float(np.median(ratios)) if len(ratios) else None), len(ratios)


def cell_ratios(static: np.ndarray, anchors: np.ndarray, cameras: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """(nearest-depth ratio [M], median-depth ratio [M]): for every sparse point a view sees on a
    cell the cloud covers, the cloud's nearest / median depth in that cell over the point's depth."""
    nearest, median = [], []
    for cam in _views(cameras):
        cells, z = _cells(cam, static)
        if not len(cells):
            continue
        order = np.lexsort((z, cells))  # by cell, then depth: per cell, first = nearest
        cells, z = cells[order], z[order]
        occupied, first, counts = np.unique(cells, return_index=True, return_counts=True)
        low, high = first + (counts - 1) // 2, first + counts // 2  # the middle one or two of each cell
        cell_median = 0.5 * (z[low] + z[high])
        a_cells, a_z = _cells(cam, anchors)
        slot = np.searchsorted(occupied, a_cells).clip(max=len(occupied) - 1)
        covered = occupied[slot] == a_cells
        nearest.append(z[first[slot[covered]]] / a_z[covered])
        median.append(cell_median[slot[covered]] / a_z[covered])
    if not nearest:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(nearest), np.concatenate(median)


def depth_error_to_anchors(static: np.ndarray, anchors: np.ndarray, cameras: Sequence) -> float | None:
    """Median |median cloud depth per cell / sparse-point depth - 1| (None: no comparison)."""
    _, median = cell_ratios(static, anchors, cameras)
    return float(np.median(np.abs(median - 1))) if len(median) else None


def fraction_in_bounds(static: np.ndarray, cameras: Sequence) -> float | None:
    """Fraction of (point, view) sightings whose depth lies in [near / 2, 2 far]; None without bounds."""
    inside, total = 0, 0
    for cam in _views(cameras):
        bounds = camera_bounds(cam)
        if bounds is None:
            return None
        _, z = _cells(cam, static)
        inside += int(((z >= bounds[0] / 2) & (z <= bounds[1] * 2)).sum())
        total += len(z)
    return inside / total if total else 0.0


def _reference_depth(camera, anchors: np.ndarray | None, static: np.ndarray) -> float | None:
    for points in (anchors, None, static):
        if points is None:
            bounds = camera_bounds(camera)
            if bounds is not None:
                return float(np.sqrt(bounds[0] * bounds[1]))
            continue
        if len(points):
            _, z = _cells(camera, points)
            if len(z):
                return float(np.median(z))
    return None


def dynamic_spread(groups: Sequence[DynamicGroup], anchors: np.ndarray | None, static: np.ndarray) -> list[float]:
    """Spread ratio of each group (see the module docstring); groups without a reference are skipped."""
    out = []
    for group in groups:
        points = np.asarray(group.points, np.float64).reshape(-1, 3)
        pixels = int(np.asarray(group.mask, bool).sum())
        depth = _reference_depth(group.camera, anchors, static)
        if len(points) < 2 or pixels == 0 or not depth:
            continue
        focal = float(group.camera.K[0, 0])
        radius = np.sqrt(pixels / np.pi) * depth / focal
        rms = float(np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean())) if np.isfinite(points).all() else 0.0
        out.append(rms * np.sqrt(2.0) / radius)
    return out


def prior_residual(fits: Mapping, field_held_out: Mapping[str, float] | None = None) -> dict | None:
    """{"held_out", "inliers", "all"}: medians over the sparse fits of the depth prior's residuals
    (module docstring), or None without a sparse fit.

    "held_out" is the median over the frames that have one (None: no frame has enough points to
    hold half out; the check then gates on "all", in sample, and says so).
    fits: the alignment report's "fits" (reflow_plugin.disparity.summary plus "frames": {name:
    FrameFit.as_dict()}); field_held_out: {frame name: held-out residual of affine fit + field}
    for the frames whose disparity the smooth correction changed (their fits' own held-out
    residual was measured on the corrected disparity, fitted to the same points)."""
    frames = {name: f for name, f in (fits.get("frames") or {}).items() if f.get("source") == "sparse"}
    if not frames:
        return None
    field_held_out = field_held_out or {}
    held = [field_held_out.get(name, f.get("held_out")) for name, f in frames.items()]

    def median(values) -> float | None:
        values = [v for v in values if v is not None]
        return float(np.median(values)) if values else None

    return {"held_out": median(held), "inliers": median(f.get("residual") for f in frames.values()),
            "all": median(f.get("residual_all") for f in frames.values())}


def check_initial_cloud(static: np.ndarray, groups: Sequence[DynamicGroup], cameras: Sequence,
                        anchors: np.ndarray | None = None, fit_residual: Mapping | None = None,
                        max_fit_residual: float = 0.0, max_depth_error: float = 0.0,
                        depth_error_flag: str = "--canonical_max_depth_error") -> CloudCheck:
    """The measurements of the module docstring; the first failing one names the failure.

    fit_residual: the depth prior's residuals (prior_residual; None: not on that path), gated on
    its "held_out" entry. max_depth_error: limit of the cloud's depth error against the sparse
    points (0 = not checked), set by the flag `depth_error_flag` (named in the failure)."""
    static = _subsample(static, MAX_POINTS)
    anchors = None if anchors is None or len(anchors) == 0 else _subsample(anchors, MAX_POINTS, 1)
    measurements: dict = {"static_points": len(static)}
    if fit_residual is not None:
        held_out = fit_residual.get("held_out")
        gated, where = ((held_out, "on points held out by image region") if held_out is not None else
                        (fit_residual.get("all"), "in sample (too few points per frame to hold half out)"))
        measurements.update(fit_residual=gated, fit_residual_held_out=held_out is not None,
                            fit_residual_inliers=fit_residual.get("inliers"), fit_residual_all=fit_residual.get("all"))
        if max_fit_residual > 0 and gated is not None and gated > max_fit_residual:
            measurements["depth_prior_rejected"] = True
            return CloudCheck(False, f"the depth prior disagrees with the sparse points: {where} its per-frame fits "
                                     f"leave a median relative depth error of {gated:.1%} (need <= "
                                     f"{max_fit_residual:.0%}, --canonical_max_fit_residual)", measurements)
    if not len(static) or not np.isfinite(static).all():
        return CloudCheck(False, "the static cloud is empty or not finite", measurements)
    coverage = check_cloud_against_cameras(static, cameras)
    measurements["views_seeing"] = coverage.views_seeing
    if coverage.views_seeing < MIN_VIEWS:
        return CloudCheck(False, f"only {coverage.views_seeing:.0%} of the training views see a static point "
                                 f"(need {MIN_VIEWS:.0%})", measurements)
    if anchors is not None:
        ratio, count = depth_ratio_to_anchors(static, anchors, cameras)
        measurements.update(depth_ratio=ratio, depth_comparisons=count)
        lo, hi = DEPTH_RATIO
        if ratio is not None and not lo <= ratio <= hi:
            return CloudCheck(False, f"static depth is {ratio:.3g}x the sparse points' (median over {count} "
                                     f"points; need {lo}-{hi}x)", measurements)
        error = depth_error_to_anchors(static, anchors, cameras)
        measurements["depth_error"] = error
        if max_depth_error > 0 and error is not None and error > max_depth_error:
            measurements["depth_prior_rejected"] = True
            return CloudCheck(False, f"the cloud's depth disagrees with the sparse points: median relative error "
                                     f"{error:.1%} per covered cell (need <= {max_depth_error:.0%}, "
                                     f"{depth_error_flag})", measurements)
    else:
        share = fraction_in_bounds(static, cameras)
        measurements["in_bounds"] = share
        if share is not None and share < MIN_IN_BOUNDS:
            return CloudCheck(False, f"only {share:.0%} of the static points lie within the dataset's near/far "
                                     f"bounds (need {MIN_IN_BOUNDS:.0%})", measurements)
    spreads = dynamic_spread(groups, anchors, static)
    if spreads:
        spread = float(np.median(spreads))
        measurements.update(dynamic_spread=spread, dynamic_groups=len(spreads))
        if spread < MIN_SPREAD:
            return CloudCheck(False, f"the dynamic cloud is collapsed: spread {spread:.3g}x the object's image "
                                     f"footprint at the scene's depth (median over {len(spreads)} keyframes; "
                                     f"need {MIN_SPREAD})", measurements)
    return CloudCheck(True, None, measurements)


__all__ = ["CloudCheck", "DynamicGroup", "cell_ratios", "check_initial_cloud", "depth_error_to_anchors",
           "depth_ratio_to_anchors", "dynamic_spread", "fraction_in_bounds", "prior_residual"]
