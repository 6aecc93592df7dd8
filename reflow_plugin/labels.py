"""Static/dynamic labels: where motion masks come from, and which initial points are dynamic.

    masks, source = training_masks(cameras, "auto", cache_dir)    # [H, W] bool per training camera
    depths = aligned_depths(cameras, static_points, masks)        # metric depth per camera, or None
    is_dynamic = vote_labels(points, cameras, masks, depths, 0.5) # [P] bool

Mask sources, in order for "auto": the dataset's `motion_masks/` (every training camera has one);
otherwise masks estimated from DIS optical flow and the known cameras
(`baselines.data.motion_masks`, with the dataset's disparity aligned to metric depth when it has
one), cached as PNGs in `<cache_dir>/motion_masks/` with a JSON key, so a second run reads them.
On a wide rig read monocularly (reflow_plugin.rig: camera poses recur, consecutive frames tens
of degrees apart) each rig camera's frames are paired among themselves, in time order: time
neighbours are other rig cameras, where DIS fails, while between two frames of one fixed camera
the static scene's flow is zero. CMU Panoptic basketball at -r 4 against its person masks
(seg/, pixels pooled; benchmarks/rig_pairs.py): time order flagged 1.4% of the pixels, IoU 0.02;
per camera 7.6% (truth 9.1%), IoU 0.42, precision 0.65, recall 0.54.

Disparity alignment: monocular disparity (NVIDIA's `disp/*.npy`) has an unknown scale and shift
per frame, fitted in inverse depth to the static points that project into the frame (outside its
mask), robustly, with the dataset's bounds as fallback (reflow_plugin.disparity).

Vote: a point is dynamic when, among the training views that see it (in front, inside the image
and, with depth, not behind the surface), at least `threshold` of them have it inside the mask.
This labels objects that stay in place (a balloon drifting, an umbrella turning). A fast mover's
points from one frame fall outside the masks of the others, so the host's static cloud is never
relabelled by it; such objects get SEEDED dynamic points (seeding.py).
"""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from baselines.data import Camera
from baselines.data.motion_masks import MotionMaskOptions, estimate_motion_masks

from .disparity import fit_frames, project  # noqa: F401 (project: re-exported)
from .rig import pose_groups, wide_rig

log = logging.getLogger(__name__)
EMPTY_DATASET_MASKS = "dataset (every mask empty: no moving pixel)"  # results.json["reflow"]["mask_source"]
CACHE_VERSION = 1
DEFAULT_OFFSETS = MotionMaskOptions().offsets  # (-2, -1, 1, 2)


class LabelError(ValueError):
    """Labels were asked from a source that does not exist for this dataset."""


def _np(tensor) -> np.ndarray:
    return tensor.detach().cpu().double().numpy()


def dataset_masks(cameras: Sequence[Camera]) -> list[np.ndarray] | None:
    """The dataset's masks ([H, W] bool) when every camera has one, else None."""
    if not cameras or any(c.mask is None for c in cameras):
        return None
    return [c.mask.detach().cpu().numpy() > 0.5 for c in cameras]


def _cache_key(cameras: Sequence[Camera], with_depth: bool, offsets: Sequence[int] = DEFAULT_OFFSETS,
               depths: Sequence[np.ndarray] | None = None, slow_offsets: Sequence[int] = (),
               rig: bool = False) -> str:
    # the default offsets leave the key as it was (masks cached by earlier runs stay valid)
    extra = "" if tuple(offsets) == DEFAULT_OFFSETS else f"|offsets={','.join(map(str, offsets))}"
    extra += "|rig cameras paired among themselves" if rig else ""
    if slow_offsets:
        slow = MotionMaskOptions(slow_offsets=tuple(slow_offsets))
        extra += f"|slow={','.join(map(str, slow_offsets))}|{slow.slow_min_error_px}|{slow.slow_gate}"
    h = hashlib.sha256(f"v{CACHE_VERSION}|depth={with_depth}{extra}".encode())
    for cam in cameras:
        h.update(f"{cam.image_name}|{cam.width}x{cam.height}|".encode())
        h.update(np.ascontiguousarray(_np(cam.viewmat)).tobytes())
        h.update(np.ascontiguousarray(cam.image.detach().cpu().numpy()[::8, ::8]).tobytes())
    for depth in depths or []:  # the depth the test reads (another disparity correction: another key)
        h.update(np.ascontiguousarray(np.asarray(depth, np.float32)[::4, ::4]).tobytes())
    return h.hexdigest()[:16]


def estimated_masks(cameras: Sequence[Camera], cache_dir: Path | None,
                    depths: Sequence[np.ndarray] | None = None,
                    offsets: Sequence[int] = DEFAULT_OFFSETS,
                    slow_offsets: Sequence[int] = ()) -> list[np.ndarray]:
    """Masks from flow vs cameras (sorted by time for the pairing; each frame tested against the
    frames `offsets` away in that order; on a rig, in its own camera's frames: `pairing_sequences`),
    cached under `cache_dir`. `slow_offsets`: the second, slow-motion pairing
    (baselines.data.motion_masks, MotionMaskOptions.slow_offsets; empty: off)."""
    sequences = pairing_sequences(cameras)
    key = _cache_key(cameras, depths is not None, offsets, depths, slow_offsets, rig=len(sequences) > 1)
    folder = None if cache_dir is None else Path(cache_dir) / "motion_masks"
    if folder is not None and (folder / "key.json").is_file():
        try:
            stored = json.loads((folder / "key.json").read_text())
            if stored.get("key") == key:
                masks = [cv2.imread(str(folder / f"{c.image_name}.png"), cv2.IMREAD_GRAYSCALE) for c in cameras]
                if all(m is not None and m.shape == (c.height, c.width) for m, c in zip(masks, cameras)):
                    log.info("motion masks: read %d cached estimates from %s", len(masks), folder)
                    return [m > 127 for m in masks]
        except (OSError, json.JSONDecodeError):
            pass
    options = MotionMaskOptions(offsets=tuple(int(o) for o in offsets),
                                slow_offsets=tuple(int(o) for o in slow_offsets))
    masks: list[np.ndarray] = [None] * len(cameras)  # type: ignore[list-item]
    for order in sequences:
        images = [cameras[i].image.detach().cpu().numpy() for i in order]
        Ks = [_np(cameras[i].K) for i in order]
        viewmats = [_np(cameras[i].viewmat) for i in order]
        ordered_depths = None if depths is None else [depths[i] for i in order]
        ordered, _ = estimate_motion_masks(images, Ks, viewmats, ordered_depths, options)
        for rank, index in enumerate(order):
            if masks[index] is None:  # a rig camera seen once is also in the time-ordered sequence, listed last
                masks[index] = ordered[rank]
    log.info("motion masks: estimated from optical flow (%s test%s), mean coverage %.3f",
             "re-projection" if depths is not None else "epipolar",
             ", each rig camera's frames paired among themselves" if len(sequences) > 1 else "",
             float(np.mean([m.mean() for m in masks])))
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        for mask, cam in zip(masks, cameras):
            cv2.imwrite(str(folder / f"{cam.image_name}.png"), mask.astype(np.uint8) * 255)
        tmp = folder / "key.json.tmp"
        tmp.write_text(json.dumps({"key": key, "depth": depths is not None}))
        tmp.replace(folder / "key.json")
    return masks


def pairing_sequences(cameras: Sequence[Camera]) -> list[list[int]]:
    """Camera indices in the time-ordered sequences the mask estimate pairs frames in: all frames
    in time order, or on a wide rig (reflow_plugin.rig) one sequence per recurring camera pose, plus
    the time-ordered sequence of every frame last when some pose occurs once (those frames keep it)."""
    order = sorted(range(len(cameras)), key=lambda i: (cameras[i].time, cameras[i].frame_index))
    viewmats = [_np(cameras[i].viewmat) for i in order]
    if not wide_rig(viewmats):
        return [order]
    groups = pose_groups(viewmats)
    sequences = [[order[r] for r in np.flatnonzero(groups == g)] for g in range(int(groups.max()) + 1)]
    recurring = [s for s in sequences if len(s) > 1]
    return recurring + ([order] if len(recurring) < len(sequences) else [])


def training_masks(cameras: Sequence[Camera], source: str, cache_dir: Path | None,
                   depths: Sequence[np.ndarray] | None = None,
                   offsets: Sequence[int] = DEFAULT_OFFSETS,
                   slow_offsets: Sequence[int] = ()) -> tuple[list[np.ndarray] | None, str]:
    """(masks or None, where they came from) for `source` in auto | masks | estimate | none;
    `offsets`, `slow_offsets`: the estimate's frame pairings (`estimated_masks`)."""
    if source == "none":
        return None, "none"
    from_dataset = dataset_masks(cameras)
    if from_dataset is not None and source in ("masks", "auto") and not any(m.any() for m in from_dataset):
        log.warning("the dataset's motion masks mark no moving pixel in any of the %d training views: nothing "
                    "is treated as moving (label_source=estimate estimates masks instead)", len(cameras))
        return from_dataset, EMPTY_DATASET_MASKS
    if source == "masks":
        if from_dataset is None:
            missing = sum(c.mask is None for c in cameras)
            raise LabelError(f"label_source=masks: {missing} of {len(cameras)} training views have no motion mask "
                             "(the dataset has no motion_masks/ folder); use label_source=estimate or auto")
        return from_dataset, "dataset"
    if source == "auto" and from_dataset is not None:
        return from_dataset, "dataset"
    if len(cameras) < 2:
        return None, "none (a single view has no flow to test)"
    return estimated_masks(cameras, cache_dir, depths, offsets, slow_offsets), "estimated"


def aligned_depths(cameras: Sequence[Camera], static_points: np.ndarray,
                   masks: Sequence[np.ndarray] | None = None) -> list[np.ndarray] | None:
    """Metric z-depth [H, W] per camera from its disparity fitted to the static points, or None.

    Each frame's affine inverse-depth fit (reflow_plugin.disparity.fit_frames: sparse points, else
    the dataset's near/far bounds, else a neighbour's depth range). static_points: [P, 3] metric
    points (may be empty: the bounds alone). None when any camera lacks disparity or a frame has no
    fit at all. Pixels whose fitted inverse depth is not positive get +inf depth (no evidence).
    """
    if not cameras or any(c.disparity is None for c in cameras):
        return None
    disparities = [cam.disparity.detach().cpu().numpy().astype(np.float64) for cam in cameras]
    fits = fit_frames(cameras, disparities, static_points, masks)
    if not all(fit.usable for fit in fits):
        missing = next(cam.image_name for cam, fit in zip(cameras, fits) if not fit.usable)
        log.info("disparity of %s could not be aligned to the static points; no depth used", missing)
        return None
    return [np.nan_to_num(fit.depth(d), nan=np.inf) for fit, d in zip(fits, disparities)]


def vote_labels(points: np.ndarray, cameras: Sequence[Camera], masks: Sequence[np.ndarray],
                depths: Sequence[np.ndarray] | None = None, threshold: float = 0.5,
                depth_tolerance: float = 0.05) -> np.ndarray:
    """[P] bool: dynamic when inside the mask in >= `threshold` of the views that see the point.

    A view sees a point when it is in front, projects inside the image and (with `depths`) is
    not more than `depth_tolerance` (relative) behind the view's surface. Points seen by no view
    are static.
    """
    points = np.asarray(points, np.float64)
    inside_mask = np.zeros(len(points))
    seen_by = np.zeros(len(points))
    for k, cam in enumerate(cameras):
        x, y, z = project(points, cam)
        col, row = np.floor(x).astype(int), np.floor(y).astype(int)
        seen = (z > 1e-6) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        if depths is not None:
            surface = depths[k][row[seen], col[seen]]
            seen[seen] = z[seen] <= surface * (1.0 + depth_tolerance)
        seen_by += seen
        inside_mask[seen] += masks[k][row[seen], col[seen]]
    return (seen_by > 0) & (inside_mask >= threshold * np.maximum(seen_by, 1))
