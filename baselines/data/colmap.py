"""COLMAP layout: `sparse/0/{cameras,images,points3D}.{bin,txt}` and `images/`.

Read with `pycolmap.Reconstruction`. COLMAP already uses our camera convention (world->camera,
OpenCV axes, pixel centres at +0.5), so poses and intrinsics are taken as they are. PINHOLE and
SIMPLE_PINHOLE cameras are exact; SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV are read with
their distortion IGNORED (a warning is logged; undistort the images with COLMAP for exact
results); other models are rejected. Images are ordered by name and timed i / (N - 1); with
`eval`, every `llffhold`-th image (by name) is a test image. points3D is the point cloud.

Optional files (both written by `python -m baselines.prepare`):
- `times.json`: `{"times": {"<image name>": t, ...}}` with t in [0, 1] for EVERY image of the
  model; replaces i / (N - 1), so frames dropped by SfM leave the others' times where they were.
- `motion_masks/<image stem>.png`: per-image motion mask (non-zero = moving), one per image.
- `gt/motion_masks/<image stem>.png`: ground-truth masks for EVALUATION only (e.g. a DAVIS clip's
  annotations, written by `benchmarks/real_captures.py`), one per image; training never sees them.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from .colmap_compat import (DISTORTED_PINHOLE_MODELS, PINHOLE_MODELS, camera_model_name, image_cam_from_world,
                            read_reconstruction)
from .errors import DatasetError
from .geometry import orthonormal_rotation
from .image_io import IMAGE_EXTENSIONS, list_files
from .pointcloud import PointCloud
from .scene_info import SceneInfo, assemble_scene, llff_holdout
from .validation import require_finite
from .views import ViewSpec, load_views

log = logging.getLogger(__name__)


def find_model_dir(source: Path) -> Path | None:
    """sparse/0, or sparse itself when it holds the model files directly."""
    for folder in (source / "sparse" / "0", source / "sparse"):
        if any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return folder
    return None


def _intrinsics(camera, source: str, warned: set[str]) -> np.ndarray:
    model = camera_model_name(camera)
    if model not in PINHOLE_MODELS + DISTORTED_PINHOLE_MODELS:
        raise DatasetError(f"{source}: camera {camera.camera_id} has model {model}; supported: "
                           f"{', '.join(PINHOLE_MODELS + DISTORTED_PINHOLE_MODELS)} (undistort the images first)")
    if model in DISTORTED_PINHOLE_MODELS and model not in warned:
        warned.add(model)
        log.warning("colmap: %s camera distortion is ignored; undistort the images for exact results", model)
    K = np.asarray(camera.calibration_matrix(), np.float64)
    require_finite(K, source, f"camera {camera.camera_id} intrinsics")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DatasetError(f"{source}: camera {camera.camera_id} has a non-positive focal length")
    return K


TIMES_FILE = "times.json"
MASK_FOLDER = "motion_masks"
TRUTH_MASK_FOLDER = "gt/motion_masks"  # evaluation only


def read_times(source: Path, names: list[str]) -> list[float] | None:
    """Per-image times from `source/times.json` (None when absent); `DatasetError` when malformed."""
    path = source / TIMES_FILE
    if not path.is_file():
        return None
    try:
        table = json.loads(path.read_text())["times"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{path}: expected {{\"times\": {{image name: time}}}} ({exc})") from None
    if not isinstance(table, dict):
        raise DatasetError(f"{path}: 'times' must map image names to times")
    times = []
    for name in names:
        if name not in table:
            raise DatasetError(f"{path} has no time for image '{name}'")
        value = table[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or not 0.0 <= value <= 1.0:
            raise DatasetError(f"{path}: time of '{name}' is {value!r}, expected a number in [0, 1]")
        times.append(float(value))
    warn_odd_times(path, names, times)
    return times


def warn_odd_times(path: Path, names: list[str], times: list[float]) -> None:
    """One warning naming frames that share a time or go back in time (image order).

    Nothing here needs distinct times (views at one time are a multi-view pair for ReFlow), but a
    copied or shuffled times.json usually is a mistake.
    """
    seen: dict[float, str] = {}
    shared, backwards = [], []
    for i, (name, t) in enumerate(zip(names, times)):
        if t in seen:
            shared.append(f"{seen[t]}/{name} ({t:g})")
        seen.setdefault(t, name)
        if i and t < times[i - 1]:
            backwards.append(f"{names[i - 1]} ({times[i - 1]:g}) -> {name} ({t:g})")
    parts = []
    if shared:
        parts.append(f"{len(shared)} frame(s) share a time: {', '.join(shared[:4])}{' ...' if len(shared) > 4 else ''}")
    if backwards:
        parts.append(f"{len(backwards)} step(s) go back in time in image order: "
                     f"{', '.join(backwards[:4])}{' ...' if len(backwards) > 4 else ''}")
    if parts:
        log.warning("%s: %s", path, "; ".join(parts))


def find_masks(source: Path, names: list[str], folder_name: str = MASK_FOLDER) -> list[Path] | None:
    """`<folder_name>/<stem>.<ext>` per image (None without the folder; only image extensions
    count); `DatasetError` for a missing one, or for two (e.g. `000.png` and `000.jpg`: which one
    the folder listing gave first would decide)."""
    folder = source / folder_name
    if not folder.is_dir():
        return None
    by_stem: dict[str, list[Path]] = {}
    for path in list_files(folder, IMAGE_EXTENSIONS):
        by_stem.setdefault(path.stem, []).append(path)
    paths = []
    for name in names:
        stem = Path(name).with_suffix("").name
        if stem not in by_stem:
            raise DatasetError(f"{folder} has no mask for image '{name}' (expected {stem}.png)")
        if len(by_stem[stem]) > 1:
            raise DatasetError(f"{folder} has {len(by_stem[stem])} masks for image '{name}': "
                               f"{', '.join(p.name for p in by_stem[stem])} (keep one)")
        paths.append(by_stem[stem][0])
    return paths


def read_colmap(source_path: Path | str, images: str = "images", resolution: int | float = -1,
                eval: bool = False, white_background: bool = False, llffhold: int = 8) -> SceneInfo:
    """Read a COLMAP scene (see the module docstring)."""
    source = Path(source_path)
    model_dir = find_model_dir(source)
    if model_dir is None:
        raise DatasetError(f"no COLMAP model in {source / 'sparse' / '0'} or {source / 'sparse'}")
    reconstruction = read_reconstruction(model_dir)
    image_dir = source / images
    if not image_dir.is_dir():
        raise DatasetError(f"missing image folder {image_dir}")
    colmap_images = sorted(reconstruction.images.values(), key=lambda im: im.name)
    if not colmap_images:
        raise DatasetError(f"COLMAP model {model_dir} has no images")
    n = len(colmap_images)
    names = [image.name for image in colmap_images]
    times = read_times(source, names)
    masks = find_masks(source, names)
    truth = find_masks(source, names, TRUTH_MASK_FOLDER)
    warned: set[str] = set()
    specs = []
    for i, image in enumerate(colmap_images):
        camera = reconstruction.cameras[image.camera_id]
        where = f"{model_dir} image '{image.name}'"
        pose = require_finite(image_cam_from_world(image), where, "pose")
        viewmat = np.eye(4)
        viewmat[:3, :3] = orthonormal_rotation(pose[:, :3], where)
        viewmat[:3, 3] = pose[:, 3]
        specs.append(ViewSpec(
            image_path=image_dir / image.name, image_name=Path(image.name).with_suffix("").as_posix(),
            K=_intrinsics(camera, str(model_dir), warned), calibrated_size=(int(camera.width), int(camera.height)),
            viewmat=viewmat, time=times[i] if times is not None else (i / (n - 1) if n > 1 else 0.0),
            frame_index=i, camera_id=int(image.camera_id), mask_path=masks[i] if masks is not None else None,
            eval_mask_path=truth[i] if truth is not None else None))
    points = np.array([p.xyz for p in reconstruction.points3D.values()], np.float64).reshape(-1, 3)
    colours = np.array([p.color for p in reconstruction.points3D.values()], np.float32).reshape(-1, 3) / 255.0
    require_finite(points, model_dir, "point coordinate")
    background = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    cameras = load_views(specs, resolution, background, same_size="camera")
    train, test = llff_holdout(n, eval, llffhold)
    return assemble_scene(cameras, train, test, dataset_type="colmap", source_path=source, num_frames=n,
                          point_cloud=PointCloud(points, colours) if len(points) else None,
                          metadata={"model_dir": str(model_dir), "image_folder": images,
                                    "times": TIMES_FILE if times is not None else "image order"})
