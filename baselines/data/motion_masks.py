"""Motion masks estimated from optical flow and KNOWN cameras (no learned model, no weights).

    masks, report = estimate_motion_masks(images, Ks, viewmats)     # list of [H, W] bool, 1 = moving

Recipe (MonST3R's idea, adapted to known cameras): for every frame and each neighbour within
`offsets`, compute DIS flow and measure how far each pixel's flow lands from where a STATIC scene
could send it:

- without depth, the distance of q + flow(q) from the epipolar line of q in the neighbour (a
  static point must land on it), or from the infinite-homography point K_b R K_a^-1 q when the
  cameras share a centre (pure rotation, where the epipolar geometry degenerates); the smaller
  of the two is taken, so the test never flags what either static model explains;
- with metric depth (`depths`, e.g. the simulator's ground truth), the distance from the point
  the depth re-projects to (MonST3R's flow-vs-rigid-flow comparison).

Each pair's error is divided by a robust scale (its median over pixels, floored at
`min_scale_px`, since most pixels are static), pixels whose flow fails the forward-backward test
are left out, the per-pixel MEDIAN over the frame's pairs is thresholded (a moving pixel breaks
every pair, a flow failure on repetitive texture usually one), and the mask is cleaned with
morphology (opening, closing, removal of small components).

Slow motion (`slow_offsets`, optional): an object that moves a fraction of a pixel per frame (an
umbrella turning in place: 0.15-0.6 px between neighbours at 128x96) stays under `min_error_px`
with the near pairs. A second median over frames 4-8 apart, with its own raw floor
(`slow_min_error_px`), adds pixels that it flags AND that the near pairs do not call static (their
normalised score above `slow_gate`): the far pairs alone also flag background that a fast object
uncovers over those frames.

Known blind spot: motion ALONG the epipolar line is invisible to the depth-free test (an object
moving parallel to the camera's translation); `report.epipolar_only` says which test ran.
`depth_consistent_errors` (used by `baselines.prepare.remask` after SfM, through
`masks_from_frame_errors`) closes most of it without a dense depth: one depth per pixel must
explain all of a frame's pairs, within bounds taken from the sparse SfM points.
Measured on the synthetic suite (128x96, full sequences, IoU with the true masks / false-positive
fraction of the image): balloon 0.55 / 0.0002 without depth, 0.91 / 0.001 with it; truck 0.003
without depth (it moves along the rig's baseline) and 0.90 / 0.014 with it; skating 0.01 and
0.45 / 0.054; static scene: empty masks either way. Give depth whenever a metric one exists.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Callable, Sequence

import cv2
import numpy as np

from .optical_flow import consistent, flow_pair, pixel_grid

PURE_ROTATION_BASELINE = 1e-9  # |t_rel| below this: the epipolar test is undefined


@dataclass
class MotionMaskOptions:
    """Knobs of `estimate_motion_masks` (defaults tuned on the synthetic suite, see tests)."""

    offsets: tuple[int, ...] = (-2, -1, 1, 2)  # neighbours (in list order) each frame is paired with
    threshold: float = 4.0  # normalised error (multiples of the pair's median) above which a pixel moves
    min_error_px: float = 1.0  # ... and at least this many pixels of mean raw error
    min_scale_px: float = 0.3  # floor of the per-pair robust scale (a static pair must not amplify noise)
    open_px: int = 1  # radius of the opening (removes isolated pixels)
    close_px: int = 2  # radius of the closing (fills holes)
    min_area: float = 0.001  # components smaller than this fraction of the image are dropped
    # optional second pairing for slow motion (an object turning in place, under a pixel per frame)
    slow_offsets: tuple[int, ...] = ()  # frames it is tested against (empty: off), e.g. (-8, -6, -4, 4, 6, 8)
    slow_min_error_px: float = 2.0  # raw error it needs (~1 px per 2-4 frames)
    slow_gate: float = 1.5  # ... and the first pairing's normalised score must exceed this (not quite static)


@dataclass
class MaskReport:
    """How each frame's mask was obtained."""

    pairs: list[list[int]] = field(default_factory=list)  # neighbours used per frame
    coverage: list[float] = field(default_factory=list)  # masked fraction per frame
    epipolar_only: bool = True
    # per frame [H, W] float32 normalised score (0 = no evidence), only when asked (keep_scores)
    scores: list[np.ndarray] = field(default_factory=list)


def relative_pose(viewmat_a: np.ndarray, viewmat_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R [3,3], t [3]) mapping camera-a coordinates to camera-b coordinates."""
    a, b = np.asarray(viewmat_a, np.float64), np.asarray(viewmat_b, np.float64)
    rotation = b[:3, :3] @ a[:3, :3].T
    return rotation, b[:3, 3] - rotation @ a[:3, 3]


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def static_scene_error(flow: np.ndarray, K_a: np.ndarray, viewmat_a: np.ndarray, K_b: np.ndarray,
                       viewmat_b: np.ndarray, depth_a: np.ndarray | None = None) -> np.ndarray:
    """[H, W] pixels: how far q + flow(q) lies from every position a static scene allows.

    With `depth_a` [H, W] (z-depth of view a's pixels): distance from the re-projected point
    (pixels with non-positive or non-finite depth, or landing behind camera b, get 0: no evidence).
    Without: min(distance from the epipolar line, distance from the infinite-homography point).
    """
    h, w = flow.shape[:2]
    x, y = pixel_grid(h, w)
    q = np.stack([x, y, np.ones_like(x)], -1).astype(np.float64)  # [H, W, 3]
    target = np.stack([x + flow[..., 0], y + flow[..., 1]], -1).astype(np.float64)
    rotation, translation = relative_pose(viewmat_a, viewmat_b)
    K_a, K_b = np.asarray(K_a, np.float64), np.asarray(K_b, np.float64)
    rays = q @ np.linalg.inv(K_a).T  # [H, W, 3], z = 1
    if depth_a is not None:
        depth = np.asarray(depth_a, np.float64)
        ok = np.isfinite(depth) & (depth > 0)
        points_b = (rays * np.where(ok, depth, 1.0)[..., None]) @ rotation.T + translation
        z = points_b[..., 2]
        ok &= z > 1e-6
        projected = points_b @ K_b.T
        predicted = projected[..., :2] / np.where(ok, z, 1.0)[..., None]
        return np.where(ok, np.linalg.norm(target - predicted, axis=-1), 0.0).astype(np.float32)

    infinite = rays @ rotation.T @ K_b.T
    infinite = infinite[..., :2] / np.clip(infinite[..., 2:3], 1e-9, None)
    homography_error = np.linalg.norm(target - infinite, axis=-1)
    if np.linalg.norm(translation) < PURE_ROTATION_BASELINE:
        return homography_error.astype(np.float32)
    fundamental = np.linalg.inv(K_b).T @ _skew(translation) @ rotation @ np.linalg.inv(K_a)
    lines = q @ fundamental.T  # [H, W, 3]: epipolar line of q in b
    norm = np.linalg.norm(lines[..., :2], axis=-1)
    target_h = np.concatenate([target, np.ones_like(target[..., :1])], -1)
    epipolar = np.abs((lines * target_h).sum(-1)) / np.clip(norm, 1e-12, None)
    epipolar = np.where(norm > 1e-12, epipolar, np.inf)
    return np.minimum(epipolar, homography_error).astype(np.float32)


def depth_consistent_errors(flows: Sequence[np.ndarray], reliable: Sequence[np.ndarray], K_a: np.ndarray,
                            viewmat_a: np.ndarray, Ks_b: Sequence[np.ndarray], viewmats_b: Sequence[np.ndarray],
                            min_inverse_depth: np.ndarray | float = 0.0,
                            parallax_tolerance: float = 0.0,
                            max_inverse_depth: np.ndarray | float = np.inf,
                            fallback_errors: Sequence[np.ndarray] | None = None) -> list[np.ndarray]:
    """Per pair [H, W] pixels: how far q + flow_k(q) lies from where ONE static point on q's ray,
    shared by every pair, would land in view b_k.

    A static pixel has one depth: each pair's flow gives it an inverse depth w_k (its position
    along the epipolar line), and one w explains all pairs. A pixel moving along the epipolar
    lines fits a line position per pair, but no single depth unless its motion mimics parallax
    (constant velocity parallel to the camera's); then its apparent depth is wrong instead: an
    object the camera follows (flow near zero while the background streams past) or one moving
    the camera's way fits only a depth beyond the static scene around it. So w is bounded to
    [`min_inverse_depth`, `max_inverse_depth`] ([H, W] or scalars, e.g.
    `farthest_static_inverse_depth` / `nearest_static_inverse_depth` of the sparse points) and
    chosen per pixel among the pairs' w_k (clamped to the bounds) as the one with the smallest
    median error over the reliable pairs.

    Args:
        flows: per partner [H, W, 2] flow a -> b_k; reliable: per partner [H, W] bool (pixels
            whose flow is trusted; the others do not vote for w but still get an error).
        K_a, viewmat_a: [3, 3] intrinsics and [4, 4] world->camera of view a; Ks_b, viewmats_b: per partner.
        parallax_tolerance: where w needed no clamping, the error is divided by
            1 + parallax_tolerance * (the point's parallax in pixels, its distance from the point at
            infinity): near static surfaces show residuals that grow with their parallax (pose and
            calibration errors); 0 = plain pixels.
        fallback_errors: optional per partner [H, W] error of another static model (e.g. the F / H
            fitted to the flow, `baselines.prepare.masks.uncalibrated_error`); where w needed no
            clamping the smaller of the two counts: a static surface that the cameras' small pose
            or focal errors misplace but a fitted F explains is not flagged, while a pixel that
            violates the depth bound keeps its error.
    Returns:
        one [H, W] float32 error per partner (inf where the chosen point is behind camera b_k).
    """
    if not flows:
        return []
    h, w = flows[0].shape[:2]
    x, y = pixel_grid(h, w)
    rays = np.stack([x, y, np.ones_like(x)], -1).astype(np.float64) @ np.linalg.inv(np.asarray(K_a, np.float64)).T
    floor = np.broadcast_to(np.maximum(np.asarray(min_inverse_depth, np.float64), 0.0), (h, w))
    ceiling = np.maximum(np.broadcast_to(np.asarray(max_inverse_depth, np.float64), (h, w)), floor)
    targets, near, shift = [], [], []  # per pair: [H, W, 2] target; K_b R r [H, W, 3]; K_b t [3]
    fitted = []
    for flow, K_b, viewmat_b in zip(flows, Ks_b, viewmats_b):
        rotation, translation = relative_pose(viewmat_a, viewmat_b)
        K_b = np.asarray(K_b, np.float64)
        A = rays @ (K_b @ rotation).T  # the point at infinity (w = 0), homogeneous in b
        B = K_b @ translation  # how the point moves per unit of inverse depth
        target = np.stack([x + flow[..., 0], y + flow[..., 1]], -1).astype(np.float64)
        # target * (A_z + w B_z) = A_xy + w B_xy, least squares in w (two equations per pixel)
        u = B[:2] - target * B[2]
        v = target * A[..., 2:3] - A[..., :2]
        fitted.append((u * v).sum(-1) / np.clip((u * u).sum(-1), 1e-18, None))
        targets.append(target)
        near.append(A)
        shift.append(B)

    def errors_at(inverse_depth: np.ndarray, tolerant: np.ndarray | None = None) -> np.ndarray:
        """[pairs, H, W] pixels between each target and the point at `inverse_depth` [H, W]; where
        `tolerant` ([H, W] bool), divided by 1 + parallax_tolerance * the point's parallax."""
        out = []
        for target, A, B in zip(targets, near, shift):
            point = A + inverse_depth[..., None] * B
            ahead = point[..., 2] > 1e-9
            projected = point[..., :2] / np.where(ahead, point[..., 2], 1.0)[..., None]
            error = np.linalg.norm(target - projected, axis=-1)
            if parallax_tolerance > 0 and tolerant is not None:
                far = A[..., :2] / np.clip(A[..., 2:3], 1e-9, None)
                error = np.where(tolerant, error / (1.0 + parallax_tolerance * np.linalg.norm(projected - far, axis=-1)),
                                 error)
            out.append(np.where(ahead, error, np.inf))
        if fallback_errors is not None and tolerant is not None:
            out = [np.where(tolerant, np.minimum(error, other), error) for error, other in zip(out, fallback_errors)]
        return np.stack(out)

    votes = np.stack([np.asarray(ok, bool) for ok in reliable])  # [pairs, H, W]
    best_cost = np.full((h, w), np.inf)
    best = errors_at(floor)  # no reliable vote: the bound itself
    for fit in fitted:
        fit = np.nan_to_num(fit, nan=0.0, posinf=0.0, neginf=0.0)
        candidate = np.clip(fit, floor, ceiling)
        # the tolerance is for static surfaces near the camera, whose residual grows with their
        # parallax (pose and calibration errors); a pixel that needed the bound gets none
        errors = errors_at(candidate, candidate == fit)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            cost = np.nanmedian(np.where(votes, errors, np.nan), axis=0)
        better = np.nan_to_num(cost, nan=np.inf) < best_cost
        best_cost = np.where(better, cost, best_cost)
        best = np.where(better[None], errors, best)
    return [error.astype(np.float32) for error in best]


def _points_in_view(points_xy: np.ndarray, inverse_depths: np.ndarray,
                    shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xy [N, 2] float64, inverse depths [N] float64, keep [N] bool): the sparse points usable as
    depth bounds, finite, in front of the camera and inside the [H, W] view."""
    h, w = shape
    inverse_depths = np.asarray(inverse_depths, np.float64)
    xy = np.asarray(points_xy, np.float64).reshape(-1, 2)
    keep = np.isfinite(inverse_depths) & (inverse_depths > 0) & np.isfinite(xy).all(1)
    keep &= (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
    return xy, inverse_depths, keep


def nearest_static_inverse_depth(points_xy: np.ndarray, inverse_depths: np.ndarray, shape: tuple[int, int],
                                 radius_px: int, margin: float) -> np.ndarray:
    """[H, W] upper bound on a static pixel's inverse depth: the largest inverse depth (the nearest
    point) within `radius_px`, divided by `margin`; the view's 95th percentile / margin where no
    point is that close; inf without points."""
    xy, inverse_depths, keep = _points_in_view(points_xy, inverse_depths, shape)
    if not keep.any():
        return np.full(shape, np.inf, np.float32)
    grid = np.full(shape, -np.inf, np.float32)
    np.maximum.at(grid, (xy[keep, 1].astype(int), xy[keep, 0].astype(int)), inverse_depths[keep].astype(np.float32))
    nearest = cv2.dilate(grid, np.ones((2 * radius_px + 1,) * 2, np.uint8), borderType=cv2.BORDER_CONSTANT,
                         borderValue=-np.inf)
    fallback = float(np.percentile(inverse_depths[keep], 95))
    return (np.where(np.isfinite(nearest), nearest, fallback) / margin).astype(np.float32)


def farthest_static_inverse_depth(points_xy: np.ndarray, inverse_depths: np.ndarray, shape: tuple[int, int],
                                  radius_px: int, margin: float) -> np.ndarray:
    """[H, W] lower bound on a static pixel's inverse depth from a view's sparse points.

    `points_xy` [N, 2] pixel positions and `inverse_depths` [N] (1 / z in that view) of the SfM
    points it observes. Each pixel gets the smallest inverse depth (the farthest point) within a
    square of half-size `radius_px`, times `margin` (< 1: room for static surfaces behind the
    points seen nearby); pixels with no point that close get the view's 5th percentile, times
    `margin`. No points at all: 0 (no bound).
    """
    xy, inverse_depths, keep = _points_in_view(points_xy, inverse_depths, shape)
    if not keep.any():
        return np.zeros(shape, np.float32)
    grid = np.full(shape, np.inf, np.float32)
    columns, rows = xy[keep, 0].astype(int), xy[keep, 1].astype(int)
    np.minimum.at(grid, (rows, columns), inverse_depths[keep].astype(np.float32))
    # erosion of a float image = the minimum over the kernel; inf where no point is within reach
    nearest = cv2.erode(grid, np.ones((2 * radius_px + 1,) * 2, np.uint8), borderType=cv2.BORDER_CONSTANT,
                        borderValue=np.inf)
    fallback = float(np.percentile(inverse_depths[keep], 5))
    return (margin * np.where(np.isfinite(nearest), nearest, fallback)).astype(np.float32)


def clean_mask(mask: np.ndarray, options: MotionMaskOptions) -> np.ndarray:
    """Opening, closing and small-component removal of a [H, W] bool mask."""
    out = mask.astype(np.uint8)
    if options.open_px > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * options.open_px + 1,) * 2)
        out = cv2.morphologyEx(out, cv2.MORPH_OPEN, kernel)
    if options.close_px > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * options.close_px + 1,) * 2)
        out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, kernel)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(out, connectivity=8)
    min_pixels = options.min_area * mask.size
    keep = np.zeros(count, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_pixels
    return keep[labels]


def estimate_motion_masks(images: Sequence[np.ndarray], Ks: Sequence[np.ndarray], viewmats: Sequence[np.ndarray],
                          depths: Sequence[np.ndarray] | None = None,
                          options: MotionMaskOptions | None = None) -> tuple[list[np.ndarray], MaskReport]:
    """Per-frame motion masks ([H, W] bool, True = moving) of a sequence with known cameras.

    Args:
        images: frames in temporal order, [H, W, 3] RGB (float in [0, 1] or uint8), one size.
        Ks, viewmats: per frame [3, 3] intrinsics and [4, 4] world->camera (OpenCV axes).
        depths: optional per-frame metric z-depth [H, W] (switches to the re-projection test).
        options: see `MotionMaskOptions`.
    Returns:
        (masks, report). A single frame has no pair: its mask is empty (report.pairs says so).
    """
    options = options or MotionMaskOptions()
    n = len(images)
    if not (len(Ks) == len(viewmats) == n) or (depths is not None and len(depths) != n):
        raise ValueError(f"estimate_motion_masks: {n} images but {len(Ks)} intrinsics, {len(viewmats)} poses"
                         + (f", {len(depths)} depth maps" if depths is not None else ""))

    def pair_error(a: int, b: int, fwd: np.ndarray) -> np.ndarray:
        return static_scene_error(fwd, Ks[a], viewmats[a], Ks[b], viewmats[b], None if depths is None else depths[a])

    masks, report = masks_from_pair_errors(images, pair_error, options)
    report.epipolar_only = depths is None
    return masks, report


PairError = Callable[[int, int, np.ndarray], np.ndarray]
# frame_errors(a, partners, flows a->b, reliable [H, W] bool per partner) -> one [H, W] error per partner
FrameErrors = Callable[[int, list[int], list[np.ndarray], list[np.ndarray]], list[np.ndarray]]


class PairFlows:
    """Forward and backward DIS flows of frame pairs, each UNORDERED pair computed once.

    Frame a is paired with a + o and, later, frame a + o with a (the offsets are symmetric), and
    both requests need the same two flows: the second one swaps the first's instead of running DIS
    twice (half of the mask estimation's time). Frames are visited in increasing order, so
    `release_before(a)` drops the pairs whose frames all lie before frame a.
    """

    def __init__(self, images: Sequence[np.ndarray]):
        self.images = images
        self.computed = 0  # DIS flow pairs run (for tests and benchmarks)
        self._flows: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(flow a -> b [H, W, 2], flow b -> a [H, W, 2])."""
        key = (min(a, b), max(a, b))
        if key not in self._flows:
            self._flows[key] = flow_pair(self.images[key[0]], self.images[key[1]])
            self.computed += 1
        lo_to_hi, hi_to_lo = self._flows[key]
        return (lo_to_hi, hi_to_lo) if a == key[0] else (hi_to_lo, lo_to_hi)

    def release_before(self, a: int) -> None:
        for key in [key for key in self._flows if key[1] < a]:
            del self._flows[key]


def _frame_scores(images: Sequence[np.ndarray], a: int, offsets: Sequence[int], frame_errors: FrameErrors,
                  min_scale_px: float, pair_flows: PairFlows | None = None
                  ) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(normalised score [H, W], raw score [H, W] in pixels, frames paired) of frame a: the per-pixel
    median over its pairs of the static-scene error, each pair's divided by its robust scale;
    pixels whose flow fails the forward-backward test in every pair score 0 (no evidence).
    `pair_flows` shares the flows with the other frames' calls (default: computed here)."""
    n = len(images)
    pair_flows = pair_flows or PairFlows(images)
    partners, flows, reliable = [], [], []
    for offset in offsets:
        b = a + offset
        if not 0 <= b < n or b == a:
            continue
        fwd, bwd = pair_flows(a, b)
        partners.append(b)
        flows.append(fwd)
        reliable.append(consistent(fwd, bwd))
    normalised, raw, pairs = [], [], []
    errors = frame_errors(a, partners, flows, reliable) if partners else []
    for b, error, ok in zip(partners, errors, reliable):
        ok = ok & np.isfinite(error)
        if not ok.any():
            continue
        scale = max(float(np.median(error[ok])), min_scale_px)
        normalised.append(np.where(ok, error / scale, np.nan))
        raw.append(np.where(ok, error, np.nan))
        pairs.append(b)
    shape = np.asarray(images[a]).shape[:2]
    if not normalised:
        return np.zeros(shape), np.zeros(shape), pairs
    # The median over pairs: a moving pixel breaks every pair, a flow failure (repetitive texture, a
    # large jump) usually only one.
    with warnings.catch_warnings():  # all-NaN pixels (unreliable in every pair) -> 0
        warnings.simplefilter("ignore", RuntimeWarning)
        score = np.nan_to_num(np.nanmedian(np.stack(normalised), axis=0), nan=0.0)
        raw_score = np.nan_to_num(np.nanmedian(np.stack(raw), axis=0), nan=0.0)
    return score, raw_score, pairs


def masks_from_pair_errors(images: Sequence[np.ndarray], pair_error: PairError,
                           options: MotionMaskOptions | None = None,
                           keep_scores: bool = False) -> tuple[list[np.ndarray], MaskReport]:
    """Masks of `images` from a per-pair static-scene error (the recipe of the module docstring).

    `pair_error(a, b, flow_a_to_b)` returns [H, W] pixels: how far each pixel of frame a lands
    from where a static scene allows in frame b (camera-aware here; `baselines.prepare.masks`
    passes an uncalibrated, fitted-geometry version). Images must share one size. `keep_scores`:
    `report.scores` holds each frame's normalised score (the median over its pairs, see
    `_frame_scores`), for refinements that need to know which pixels the geometry calls static.
    """
    def frame_errors(a: int, partners: list[int], flows: list[np.ndarray], _reliable) -> list[np.ndarray]:
        return [pair_error(a, b, flow) for b, flow in zip(partners, flows)]

    return masks_from_frame_errors(images, frame_errors, options, keep_scores)


def masks_from_frame_errors(images: Sequence[np.ndarray], frame_errors: FrameErrors,
                            options: MotionMaskOptions | None = None,
                            keep_scores: bool = False) -> tuple[list[np.ndarray], MaskReport]:
    """`masks_from_pair_errors` for tests that judge a frame's pairs jointly (one depth per pixel
    shared by all pairs, `depth_consistent_errors`): `frame_errors(a, partners, flows, reliable)`
    gets every flow of frame a at once and returns one [H, W] error (pixels) per partner."""
    options = options or MotionMaskOptions()
    n = len(images)
    if n == 0:
        return [], MaskReport()
    shape = np.asarray(images[0]).shape[:2]
    for k, image in enumerate(images):
        if np.asarray(image).shape[:2] != shape:
            raise ValueError(f"estimate_motion_masks: frame {k} is {np.asarray(image).shape[:2]}, frame 0 is {shape}")
    report = MaskReport(pairs=[[] for _ in range(n)])
    masks = []
    pair_flows = PairFlows(images)
    for a in range(n):
        pair_flows.release_before(a)
        score, raw_score, pairs = _frame_scores(images, a, options.offsets, frame_errors, options.min_scale_px,
                                                pair_flows)
        report.pairs[a] = pairs
        if keep_scores:
            report.scores.append(score.astype(np.float32))
        moving = (score > options.threshold) & (raw_score > options.min_error_px)
        if options.slow_offsets:
            slow, slow_raw, _ = _frame_scores(images, a, options.slow_offsets, frame_errors, options.min_scale_px,
                                              pair_flows)
            # slow motion: flagged over frames far apart, and not quite static between near ones
            moving |= ((slow > options.threshold) & (slow_raw > options.slow_min_error_px)
                       & (score > options.slow_gate))
        mask = clean_mask(moving, options) if pairs else np.zeros(shape, bool)
        masks.append(mask)
        report.coverage.append(float(mask.mean()))
    return masks, report
