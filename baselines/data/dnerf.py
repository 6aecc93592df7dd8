"""D-NeRF / Blender layout.

    <scene>/transforms_train.json, transforms_test.json (transforms_val.json is not used):
        {"camera_angle_x": fov_x (radians),            (or "fl_x" with "w", in pixels)
         "frames": [{"file_path": "./train/r_000", "time": t, "transform_matrix": 4x4}, ...]}
    transform_matrix is camera-to-world with OpenGL/Blender camera axes (x right, y up, z back).

RGBA images are composited on white (`white_background`) or black, and alpha is kept in
`extras["alpha"]`. Square pixels and a centred principal point are assumed (as in NeRF).
Times are divided by the largest time over both splits (4DGS's timeline mapping). Without
`eval` the test frames join the training set and the test set is empty (3DGS/4DGS behaviour).
A random initialisation uses 3DGS's Blender box [-1.3, 1.3]^3 (`scene_box`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import DatasetError
from .geometry import focal_from_fov, intrinsics, opengl_c2w_to_opencv, orthonormal_rotation, viewmat_from_c2w
from .nvidia import find_point_file
from .pointcloud import RawPoints
from .scene_info import SceneInfo, assemble_scene
from .validation import json_array, json_float, json_key, load_json
from .views import ViewSpec, load_views

TRAIN_FILE, TEST_FILE = "transforms_train.json", "transforms_test.json"
POINT_FILES = ("fused.ply", "points3D.ply", "points3d.ply")
BLENDER_BOX = np.array([[-1.3, -1.3, -1.3], [1.3, 1.3, 1.3]], np.float32)


def _resolve_image(source: Path, file_path: str, json_path: Path) -> Path:
    path = (source / file_path).resolve() if not Path(file_path).is_absolute() else Path(file_path)
    if path.suffix.lower() in (".png", ".jpg", ".jpeg", ".exr") and path.is_file():
        return path
    for extension in (".png", ".jpg", ".jpeg"):
        candidate = path.with_name(path.name + extension)
        if candidate.is_file():
            return candidate
    raise DatasetError(f"{json_path}: image for file_path '{file_path}' not found (tried {path} with "
                       ".png/.jpg/.jpeg)")


def _image_name(file_path: str) -> str:
    """'./train/r_000.png' -> 'train/r_000' (unique across splits, unlike the bare stem)."""
    path = Path(file_path)
    if path.suffix.lower() in (".png", ".jpg", ".jpeg", ".exr"):
        path = path.with_suffix("")
    return path.as_posix()


def _read_transforms(source: Path, name: str) -> tuple[list[dict], dict]:
    path = source / name
    data = load_json(path)
    frames = json_key(data, "frames", path)
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: 'frames' must be a non-empty list")
    parsed = []
    with_time = [isinstance(f, dict) and "time" in f for f in frames]
    if any(with_time) and not all(with_time):
        raise DatasetError(f"{path}: frame {with_time.index(False)} has no 'time' while others do")
    for i, frame in enumerate(frames):
        where = Path(f"{path} frame {i}")
        c2w = json_array(frame, "transform_matrix", where, shape=(4, 4))
        rotation = orthonormal_rotation(opengl_c2w_to_opencv(c2w[:3, :3]), str(where))
        time = json_float(frame, "time", where) if all(with_time) else 0.0
        if time < 0:
            raise DatasetError(f"{where}: negative time {time}")
        file_path = json_key(frame, "file_path", where)
        parsed.append({"viewmat": viewmat_from_c2w(rotation, c2w[:3, 3]), "time": time,
                       "file_path": str(file_path), "image": _resolve_image(source, str(file_path), path)})
    if "camera_angle_x" in data:
        fov = json_float(data, "camera_angle_x", path, positive=True)
        calib = {"fov_x": fov}
    else:
        calib = {"fl_x": json_float(data, "fl_x", path, positive=True),
                 "w": json_float(data, "w", path, positive=True)}
    return parsed, calib


def read_dnerf(source_path: Path | str, images: str = "images", resolution: int | float = -1,
               eval: bool = False, white_background: bool = False, llffhold: int = 8) -> SceneInfo:
    """Read a D-NeRF/Blender scene (see the module docstring); `images` and `llffhold` are unused."""
    source = Path(source_path)
    train_frames, calib = _read_transforms(source, TRAIN_FILE)
    test_frames: list[dict] = []
    if (source / TEST_FILE).is_file() or eval:
        test_frames, _ = _read_transforms(source, TEST_FILE)
    frames = train_frames + test_frames
    point_file = find_point_file(source, POINT_FILES)
    raw_points = None if point_file is None else RawPoints.read(point_file)

    timeline = sorted({f["time"] for f in frames})
    max_time = timeline[-1]
    frame_of_time = {t: k for k, t in enumerate(timeline)}
    # Image size is needed for the focal; all images share it (checked while loading).
    from .image_io import read_rgba
    probe, _ = read_rgba(frames[0]["image"])
    height, width = probe.shape[:2]
    if "fov_x" in calib:
        focal = focal_from_fov(calib["fov_x"], width)
    else:
        focal = calib["fl_x"] * width / calib["w"]
    K = intrinsics(focal, focal, width / 2.0, height / 2.0)
    specs = [ViewSpec(image_path=f["image"], image_name=_image_name(f["file_path"]),
                      K=K, calibrated_size=(width, height), viewmat=f["viewmat"],
                      time=f["time"] / max_time if max_time > 0 else 0.0,
                      frame_index=frame_of_time[f["time"]], camera_id=0)
             for f in frames]
    background = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    cameras = load_views(specs, resolution, background, same_size="all")
    n_train = len(train_frames)
    train = list(range(n_train)) if eval else list(range(len(frames)))
    test = list(range(n_train, len(frames))) if eval else []
    point_cloud = None if raw_points is None else raw_points.to_point_cloud([cameras[i] for i in train])
    return assemble_scene(cameras, train, test, dataset_type="dnerf", source_path=source,
                          num_frames=len(timeline), point_cloud=point_cloud, scene_box=BLENDER_BOX.copy(),
                          metadata={"max_time": max_time, "point_file": str(point_file) if point_file else None})
