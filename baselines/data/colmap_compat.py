"""The few pycolmap calls the readers need, isolated so version differences live in one place.

Version notes (pycolmap is COLMAP's Python binding; its API moved with COLMAP's rig support):
- `Image.cam_from_world` is a property up to pycolmap 3.11 and a method from 3.12 (frames/rigs);
  `image_cam_from_world` accepts both.
- `Camera.model` is an enum with `.name` in recent releases; older ones also had `model_name`.
- Triangulation with known poses (`triangulation.py`) uses `Reconstruction.add_camera_with_trivial_rig`
  and `add_image_with_trivial_frame`, which exist from pycolmap 4.0.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import DatasetError

# Models whose first parameters are pinhole (f or fx, fy, cx, cy) and whose remaining parameters
# are lens distortion, which the readers ignore (with a warning), as 3DGS/4DGS do.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
DISTORTED_PINHOLE_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def read_reconstruction(model_dir: Path):
    """`pycolmap.Reconstruction` of a folder with cameras/images/points3D (.bin or .txt)."""
    import pycolmap

    model_dir = Path(model_dir)
    missing = [n for n in ("cameras", "images", "points3D")
               if not ((model_dir / f"{n}.bin").is_file() or (model_dir / f"{n}.txt").is_file())]
    if missing:
        raise DatasetError(f"COLMAP model {model_dir} lacks {', '.join(f'{m}.bin/.txt' for m in missing)}")
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises RuntimeError/ValueError variants on corrupt files
        raise DatasetError(f"cannot read COLMAP model {model_dir}: {exc}") from exc


def camera_model_name(camera) -> str:
    model = camera.model
    return getattr(model, "name", None) or str(getattr(camera, "model_name", model))


def image_cam_from_world(image) -> np.ndarray:
    """[3,4] world->camera matrix of a pycolmap image (property or method, by version)."""
    pose = image.cam_from_world
    if callable(pose):
        pose = pose()
    return np.asarray(pose.matrix(), dtype=np.float64)


@contextlib.contextmanager
def quiet_colmap_logs(min_level: int = 1) -> Iterator[None]:
    """Raise glog's minimum level (0 INFO, 1 WARNING, 2 ERROR) while COLMAP runs, then restore."""
    import pycolmap

    logging_mod = getattr(pycolmap, "logging", None)
    if logging_mod is None or not hasattr(logging_mod, "minloglevel"):
        yield
        return
    previous = logging_mod.minloglevel
    logging_mod.minloglevel = max(previous, min_level)
    try:
        yield
    finally:
        logging_mod.minloglevel = previous
