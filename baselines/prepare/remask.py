"""Stage 6: motion masks re-estimated with the registered cameras (after mapping).

    python -m baselines.prepare.remask DATASET [-o NEW_DATASET] [--quiet]
    masks, info = posed_masks(images, Ks, viewmats, sparse)   # [H, W] bool per registered frame

The pre-SfM masks (`masks.py`) fit F / H to the flow with RANSAC, so they cannot see motion along
the epipolar lines, and a subject that the camera follows (nearly still in the frame while the
background streams past) fits them like a point at infinity. Once SfM has run the cameras are
known, and so are the depths of the static points it triangulated. This stage scores each
registered frame's pixels by `baselines.data.motion_masks.depth_consistent_errors`: one static
depth per pixel must explain the flow to every paired frame, and that depth may not lie far
beyond the sparse points seen around the pixel (`farthest_static_inverse_depth`). The per-pair
errors go through the same normalise / median / threshold / clean recipe
(`masks_from_frame_errors`) and the GrabCut snap of `masks.snap_to_edges`.

The pre-SfM masks still keep movers out of feature extraction (they are all there is before
SfM); the dataset's `motion_masks/` gets this stage's masks, and the report's "masks" entry says
which masks were written (`"stage": "posed"` or `"pre-sfm"`) and their share of pixels.

Re-running only this stage on a prepared folder: `python -m baselines.prepare.remask DATASET`
rewrites DATASET/motion_masks/ and the "masks" entry of its prepare_report.json and nothing
else; with `-o NEW` it copies the dataset (images, sparse, times.json, report) to NEW and writes
the masks there, leaving DATASET untouched.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from tqdm import tqdm

from ..data.colmap_compat import image_cam_from_world
from ..data.motion_masks import (MotionMaskOptions, clean_mask, depth_consistent_errors,
                                 farthest_static_inverse_depth, masks_from_frame_errors,
                                 nearest_static_inverse_depth)
from .errors import PrepareError
from .masks import SNAP_STATIC_SCORE, pair_step, snap_to_edges, uncalibrated_error
from .parallax import measure_parallax

# Constants, tuning-clip mean IoU of benchmarks/mask_quality.py --posed (dog, libby, goat, cows,
# scooter-black; docs/DATASETS.md has the table) and IoU on the synthetic prepare clip of
# tests/test_prepare.py (SfM cameras; its pre-SfM masks: 0.70). The threshold and raw floor are
# the pre-SfM stage's (threshold 4.0 instead: 0.708 vs 0.710 on the tuning clips other than goat).
THRESHOLD, MIN_ERROR_PX = 3.0, 0.7
BOUND_RADIUS_FRACTION = 0.1  # neighbourhood of the sparse-point depth bound, fraction of the frame width
# A static pixel may lie up to 1 / margin times beyond the farthest point nearby. 0.8 and 0.5 tie
# on the tuning clips (0.627 both, with a tolerance of 0.2 on every pixel); on the synthetic box
# moving along the epipolar lines (tests/test_prepare_remask.py) 0.5 -> 0.06, 0.7 -> 0.52, 0.8 -> 0.86.
BOUND_MARGIN = 0.8
# Residual allowed per pixel of parallax where no bound was needed (near static surfaces carry
# pose and calibration errors): tuning mean 0.583 at 0, 0.593 at 0.05, 0.611 at 0.2; synthetic
# clip 0.76, 0.73, 0.56 (the diagonally moving box is near the camera, and excused too).
PARALLAX_TOLERANCE = 0.05
# > 0: a static pixel may also lie at most 1 / margin times nearer than the nearest point nearby.
# Off: it helped in no measured case (synthetic box along the epipolar lines, bound margin 0.5:
# 0.058 off, 0.068 at 0.5, 0.044 at 0.33; its apparent depth is beyond the room, not in front).
NEAR_MARGIN = 0.0
# True: where a pixel's depth fits the bounds, the F / H fitted to the flow (the pre-SfM test) may
# excuse it (`depth_consistent_errors(fallback_errors=...)`). Off: tuning mean 0.593 -> 0.556
# with it (goat 0.21 -> 0.41, whose near rocks the cameras misplace by 6-25 px, but dog 0.75 ->
# 0.63, cows 0.85 -> 0.60: parts of a walking animal that a fitted F explains).
FITTED_FALLBACK = False


@dataclass
class SparseView:
    """What one registered frame sees of the SfM model: [N, 2] pixel positions and [N] inverse depths."""

    xy: np.ndarray
    inverse_depth: np.ndarray


def read_posed_dataset(dataset: Path) -> tuple[list[str], list[np.ndarray], list[np.ndarray], list[np.ndarray],
                                               list[SparseView]]:
    """(names, frames [H, W, 3] uint8 BGR, Ks [3, 3], viewmats [4, 4] world->camera, sparse views) of a
    prepared dataset (`images/`, `sparse/0/`), in name order (= time order for prepare's datasets)."""
    from ..data.colmap_compat import read_reconstruction
    from ..data.errors import DatasetError

    dataset = Path(dataset)
    if not (dataset / "images").is_dir():
        raise PrepareError(f"{dataset}: no images/ folder (expected a dataset written by python -m baselines.prepare)")
    model_dir = dataset / "sparse" / "0"
    try:
        model = read_reconstruction(model_dir)
    except DatasetError as err:
        raise PrepareError(str(err), "give a dataset folder written by python -m baselines.prepare") from None
    by_name = {image.name: image for image in model.images.values() if image.has_pose}
    names = sorted(p.name for p in (dataset / "images").iterdir() if p.name in by_name)
    if len(names) < 2:
        raise PrepareError(f"{dataset}: {len(names)} registered frame(s) in images/ and sparse/0; need at least 2")
    frames, Ks, viewmats, views = [], [], [], []
    for name in names:
        image = by_name[name]
        frame = cv2.imread(str(dataset / "images" / name), cv2.IMREAD_COLOR)
        if frame is None:
            raise PrepareError(f"cannot read {dataset / 'images' / name}")
        camera = model.cameras[image.camera_id]
        if (camera.width, camera.height) != (frame.shape[1], frame.shape[0]):
            raise PrepareError(f"{dataset / 'images' / name} is {frame.shape[1]}x{frame.shape[0]} but its camera "
                               f"is {camera.width}x{camera.height}")
        pose = image_cam_from_world(image)
        viewmat = np.eye(4)
        viewmat[:3] = pose
        xy, inverse = [], []
        for point in image.points2D:
            if point.has_point3D():
                z = pose[2, :3] @ model.points3D[point.point3D_id].xyz + pose[2, 3]
                if z > 0:
                    xy.append(point.xy)
                    inverse.append(1.0 / z)
        frames.append(frame)
        Ks.append(np.asarray(camera.calibration_matrix(), np.float64))
        viewmats.append(viewmat)
        views.append(SparseView(np.asarray(xy, np.float64).reshape(-1, 2), np.asarray(inverse, np.float64)))
    return names, frames, Ks, viewmats, views


def posed_masks(images: Sequence[np.ndarray], Ks: Sequence[np.ndarray], viewmats: Sequence[np.ndarray],
                views: Sequence[SparseView] | None, frame_motion_px: float | None = None,
                threshold: float = THRESHOLD, min_error_px: float = MIN_ERROR_PX,
                bound_margin: float = BOUND_MARGIN, bound_radius_fraction: float = BOUND_RADIUS_FRACTION,
                parallax_tolerance: float = PARALLAX_TOLERANCE, near_margin: float = NEAR_MARGIN,
                fitted_fallback: bool = FITTED_FALLBACK,
                snap: bool = True, progress: bool = True) -> list[np.ndarray]:
    """Motion masks ([H, W] bool, True = moving) of registered frames in time order.

    `views`: each frame's sparse points (None or an empty view: no depth bound, the depth test
    alone); `frame_motion_px`: median background motion between consecutive frames (picks the
    pairs, as in `masks.pair_step`; measured from the frames when None).
    """
    images = [np.asarray(image) for image in images]
    if frame_motion_px is None:
        frame_motion_px = measure_parallax(images).frame_motion_px
    step = pair_step(frame_motion_px, len(images))
    options = MotionMaskOptions(offsets=(-2 * step, -step, step, 2 * step), threshold=threshold,
                                min_error_px=min_error_px)
    shape = images[0].shape[:2]
    radius = max(1, int(round(bound_radius_fraction * shape[1])))
    bar = tqdm(total=len(images), desc="motion masks (cameras)", unit="frame", disable=not progress)

    def frame_errors(a: int, partners: list[int], flows: list[np.ndarray], reliable: list[np.ndarray]):
        bar.update(1)
        floor, ceiling = 0.0, np.inf
        if views is not None and len(views[a].inverse_depth):
            floor = farthest_static_inverse_depth(views[a].xy, views[a].inverse_depth, shape, radius, bound_margin)
            if near_margin > 0:
                ceiling = nearest_static_inverse_depth(views[a].xy, views[a].inverse_depth, shape, radius, near_margin)
        fallback = [uncalibrated_error(flow) for flow in flows] if fitted_fallback else None
        return depth_consistent_errors(flows, reliable, Ks[a], viewmats[a], [Ks[b] for b in partners],
                                       [viewmats[b] for b in partners], floor, parallax_tolerance, ceiling, fallback)

    masks, report = masks_from_frame_errors(images, frame_errors, options, keep_scores=True)
    bar.close()
    if not snap:
        return masks
    static = [(score > 0) & (score < SNAP_STATIC_SCORE) for score in report.scores]
    return [clean_mask(snap_to_edges(image, mask, guard), options) for image, mask, guard in zip(images, masks, static)]


def write_masks(dataset: Path, names: Sequence[str], masks: Sequence[np.ndarray]) -> None:
    """`dataset/motion_masks/<name>` (255 = moving) for each frame, replacing the folder's previous masks."""
    folder = Path(dataset) / "motion_masks"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for name, mask in zip(names, masks):
        cv2.imwrite(str(folder / name), np.where(mask, 255, 0).astype(np.uint8))


def mask_entry(masks: Sequence[np.ndarray], pre_sfm: dict | None, seconds: float) -> dict:
    """The report's "masks" entry for the written posed masks; `pre_sfm` (the earlier entry) is kept inside."""
    cover = np.array([float(m.mean()) for m in masks] or [0.0])
    return {"source": "auto", "stage": "posed", "mean_coverage": float(cover.mean()),
            "max_coverage": float(cover.max()), "coverage": [round(float(c), 5) for c in cover],
            "seconds": round(seconds, 2), "pre_sfm": pre_sfm}


def remask(dataset: Path, output: Path | None = None, progress: bool = True) -> dict:
    """Re-estimate `dataset`'s motion masks with its cameras; write them into `output` (a copy of the
    dataset, created) or, when None, into `dataset/motion_masks/`. Returns the new "masks" entry."""
    dataset = Path(dataset)
    if output is not None:
        output = Path(output)
        if output.resolve() == dataset.resolve():
            output = None
        elif output.exists() and (not output.is_dir() or any(output.iterdir())):
            raise PrepareError(f"-o {output}: exists and is not empty", "choose a new folder")
    names, frames, Ks, viewmats, views = read_posed_dataset(dataset)  # checks before the long work
    start = time.perf_counter()
    masks = posed_masks(frames, Ks, viewmats, views, progress=progress)
    target = dataset
    if output is not None:
        output.mkdir(parents=True, exist_ok=True)
        for name in ("images", "sparse"):
            shutil.copytree(dataset / name, output / name)
        for name in ("times.json", "prepare_report.json"):
            if (dataset / name).is_file():
                shutil.copyfile(dataset / name, output / name)
        target = output
    write_masks(target, names, masks)
    report_path = target / "prepare_report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    previous = report.get("masks")
    if isinstance(previous, dict) and previous.get("stage") == "posed":
        previous = previous.get("pre_sfm")
    entry = mask_entry(masks, previous, time.perf_counter() - start)
    report["masks"] = entry
    report_path.write_text(json.dumps(report, indent=1))
    return entry


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m baselines.prepare.remask",
                                     description="Re-estimate a prepared dataset's motion masks with its cameras.")
    parser.add_argument("dataset", type=Path, help="a folder written by python -m baselines.prepare")
    parser.add_argument("-o", "--output", type=Path,
                        help="write a copy of the dataset with the new masks here (default: replace DATASET/motion_masks/)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        entry = remask(args.dataset, args.output, progress=not args.quiet)
    except PrepareError as err:
        if os.environ.get("FOURDGS_TRACEBACK") == "1":
            raise
        print(f"error: {err}", file=sys.stderr)
        return 2
    where = args.output or args.dataset
    print(f"remask: {len(entry['coverage'])} masks written to {Path(where) / 'motion_masks'} "
          f"(mean coverage {entry['mean_coverage']:.1%}, {entry['seconds']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
