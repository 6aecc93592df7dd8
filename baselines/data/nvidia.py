"""NVIDIA Dynamic Scenes in the DynamicNeRF/LLFF layout.

    <scene>/poses_bounds.npy   [N,17]: per frame a 3x5 matrix flattened row-major (camera-to-world
                               3x4 whose rotation columns are [down, right, back], then the
                               column [H, W, focal] at the ORIGINAL resolution), then near, far
    <scene>/images/            N images (or another folder named by `images`, e.g. images_2)
    <scene>/disp/*.npy         optional disparity maps, resized to the image resolution
    <scene>/motion_masks/*.png optional motion masks, 255 = dynamic
    <scene>/gt/motion_masks/*.png  optional ground-truth masks for evaluation only (the simulator
                               writes them; without motion_masks/ training never sees them)
    <scene>/points3D.ply       optional point cloud (also points3d.ply, points.npy, or sparse/0:
                               the COLMAP model LLFF poses come from shares their world frame)

Files are paired with frames by sorted name. Poses are used as stored: no recentring and no
bounds rescaling (NeRF's NDC preprocessing), so cameras stay in the file's world frame. Frames
whose poses coincide are given the same `camera_id` (the NVIDIA rig's cameras recur).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import DatasetError
from .geometry import intrinsics, llff_c2w_to_opencv, orthonormal_rotation, viewmat_from_c2w
from .image_io import IMAGE_EXTENSIONS, list_files
from .pointcloud import RawPoints
from .scene_info import SceneInfo, assemble_scene, llff_holdout
from .validation import load_npy, require_finite
from .views import ViewSpec, load_views


POSES_FILE = "poses_bounds.npy"
POINT_FILES = ("points3D.ply", "points3d.ply", "points.npy", "sparse/0")


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(viewmats [N,4,4] OpenCV world->camera, hwf [N,3] (H, W, focal), bounds [N,2]) from the file."""
    array = load_npy(path)
    if array.ndim != 2 or array.shape[1] != 17 or len(array) == 0:
        raise DatasetError(f"{path} has shape {array.shape}, expected [N, 17]")
    array = require_finite(array, path, "pose/bounds value")
    poses = array[:, :15].reshape(-1, 3, 5)
    hwf, bounds = poses[:, :, 4], array[:, 15:17]
    for i, (h, w, f) in enumerate(hwf):
        if h < 1 or w < 1 or f <= 0:
            raise DatasetError(f"{path}: frame {i} has H={h}, W={w}, focal={f} (must be positive)")
    for i, (near, far) in enumerate(bounds):
        if not 0 < near < far:
            raise DatasetError(f"{path}: frame {i} has bounds near={near}, far={far} (need 0 < near < far)")
    viewmats = np.stack([
        viewmat_from_c2w(orthonormal_rotation(llff_c2w_to_opencv(p[:, :3]), f"{path} frame {i}"), p[:, 3])
        for i, p in enumerate(poses)])
    return viewmats, hwf, bounds


def camera_ids_from_poses(viewmats: np.ndarray, tol: float = 1e-6) -> list[int]:
    """Frames with identical poses share an id (ids numbered by first appearance)."""
    ids, reps = [], []
    for v in viewmats:
        match = next((k for k, r in enumerate(reps) if np.abs(r - v).max() <= tol), None)
        if match is None:
            reps.append(v)
            match = len(reps) - 1
        ids.append(match)
    return ids


def _optional_folder(source: Path, name: str, extensions: tuple[str, ...], count: int) -> list[Path] | None:
    folder = source / name
    if not folder.is_dir():
        return None
    files = list_files(folder, extensions)
    if len(files) != count:
        raise DatasetError(f"{folder} holds {len(files)} files but {source / POSES_FILE} has {count} poses")
    return files


def _image_folder(source: Path, images: str) -> Path:
    folder = source / images
    if not folder.is_dir():
        found = sorted(p.name for p in source.glob("images*") if p.is_dir())
        raise DatasetError(f"missing image folder {folder} (found: {', '.join(found) or 'none'}; "
                           "choose one with images=...)")
    return folder


def find_point_file(source: Path, candidates: tuple[str, ...] = POINT_FILES) -> Path | None:
    for name in candidates:
        path = source / name
        if path.is_file() or (path.is_dir() and any(path.glob("points3D.*"))):
            return path
    return None


def check_poses_bounds(source: Path, images: str = "images") -> None:
    """Validate ``<source>/poses_bounds.npy`` (finite, [N, 17], sane bounds) and, when the image
    folder exists, its count against the images; one-line `DatasetError` naming the file."""
    viewmats, _, _ = read_poses_bounds(source / POSES_FILE)
    folder = source / images
    if folder.is_dir():
        count = len(list_files(folder, IMAGE_EXTENSIONS))
        if count != len(viewmats):
            raise DatasetError(f"{source / POSES_FILE} has {len(viewmats)} poses but {folder} holds {count} images")


def read_nvidia(source_path: Path | str, images: str = "images", resolution: int | float = -1,
                eval: bool = False, white_background: bool = False, llffhold: int = 8) -> SceneInfo:
    """Read a DynamicNeRF/LLFF-layout scene (see the module docstring).

    Times are i / (N - 1). With `eval`, frame i is a test frame iff i % llffhold == 0 (the LLFF
    hold-out, also the NVIDIA protocol's every 8th frame); without it every frame trains.
    """
    source = Path(source_path)
    viewmats, hwf, bounds = read_poses_bounds(source / POSES_FILE)
    n = len(viewmats)
    image_files = list_files(_image_folder(source, images), IMAGE_EXTENSIONS)
    if len(image_files) != n:
        raise DatasetError(f"{source / images} holds {len(image_files)} images but {source / POSES_FILE} "
                           f"has {n} poses")
    disp_files = _optional_folder(source, "disp", (".npy",), n)
    mask_files = _optional_folder(source, "motion_masks", IMAGE_EXTENSIONS, n)
    eval_mask_files = None if mask_files else _optional_folder(source, "gt/motion_masks", IMAGE_EXTENSIONS, n)
    camera_ids = camera_ids_from_poses(viewmats)
    point_file = find_point_file(source)
    raw_points = None if point_file is None else RawPoints.read(point_file)  # fail early if malformed
    specs = []
    for i in range(n):
        h, w, focal = hwf[i]
        specs.append(ViewSpec(
            image_path=image_files[i], image_name=image_files[i].stem,
            K=intrinsics(focal, focal, w / 2.0, h / 2.0), calibrated_size=(int(round(w)), int(round(h))),
            viewmat=viewmats[i], time=i / (n - 1) if n > 1 else 0.0, frame_index=i,
            camera_id=camera_ids[i], mask_path=mask_files[i] if mask_files else None,
            disparity_path=disp_files[i] if disp_files else None,
            eval_mask_path=eval_mask_files[i] if eval_mask_files else None,
            extras={"near_far": bounds[i].astype(np.float32)}))
    background = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    cameras = load_views(specs, resolution, background, same_size="all")
    train, test = llff_holdout(n, eval, llffhold)
    point_cloud = None if raw_points is None else raw_points.to_point_cloud([cameras[i] for i in train])
    return assemble_scene(cameras, train, test, dataset_type="nvidia", source_path=source, num_frames=n,
                          point_cloud=point_cloud, near_far=(float(bounds[:, 0].min()), float(bounds[:, 1].max())),
                          metadata={"image_folder": images, "point_file": str(point_file) if point_file else None})
