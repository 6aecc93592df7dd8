"""HyperNeRF / Nerfies layout.

    <scene>/dataset.json     {"ids": [...], "train_ids": [...], "val_ids": [...]}
    <scene>/metadata.json    {id: {"warp_id", "appearance_id", "camera_id", optional "time_id"}}
    <scene>/scene.json       {"center": [3], "scale": s, "near": n, "far": f}
    <scene>/camera/<id>.json {"orientation": 3x3 world->camera rotation (OpenCV axes),
                              "position": camera centre, "focal_length", "principal_point",
                              "image_size": [W, H] at 1x, "pixel_aspect_ratio", "skew",
                              "radial_distortion", "tangential_distortion"}
    <scene>/rgb/{N}x/<id>.png images downscaled N times
    <scene>/points.npy       optional points [P,3] (or 4DGS's points3D_downsample2.ply)

Frame: by default the raw capture frame, as 4DGS works in it (its hyper_loader reads scene.json's
center/scale but never applies them), so 4DGS HyperNeRF checkpoints and point files line up.
`reader_options={"apply_scene_transform": True}` applies the Nerfies/HyperNeRF normalisation
p -> (p - center) * scale to positions and points (near/far of scene.json are stated in that
frame and are converted accordingly); K = [[f, skew, px],
[0, f * pixel_aspect_ratio, py], [0, 0, 1]] with pixel centres at +0.5 (our convention), scaled
to the chosen rgb/{N}x images. Lens distortion is IGNORED (4DGS ignores it too); a warning is
logged when a camera has any.

Time = time_id (or warp_id when absent, as 4DGS reads it) / its maximum. Splits follow 4DGS's
hyper_loader: with non-empty val_ids ("vrig") train on train_ids and test on val_ids; otherwise
("interp") frame i trains iff i % 4 == 0 and the test frames are the training frames + 2, less
the last one. The split is the dataset's own, so it applies whether or not `eval` is set.

Resolution: rgb/{N}x is read when resolution is N (1, 2, 4, 8) and that folder exists, else the
images are derived from the finest finer folder; resolution -1 reads rgb/2x when present (the
scale 4DGS always uses), else the finest folder with the 1600-px rule; a width picks the
smallest folder at least that wide and resizes.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from .errors import DatasetError
from .geometry import intrinsics, orthonormal_rotation, viewmat_from_w2c
from .image_io import read_rgba
from .nvidia import find_point_file
from .pointcloud import RawPoints
from .scene_info import SceneInfo, assemble_scene
from .validation import json_array, json_float, json_key, load_json, require_dir
from .views import ViewSpec, load_views

log = logging.getLogger(__name__)

POINT_FILES = ("points.npy", "points3D_downsample2.ply", "points3D.ply")


def _scale_folders(source: Path) -> dict[int, Path]:
    rgb = require_dir(source / "rgb", "image folder")
    folders = {}
    for path in rgb.iterdir():
        name = path.name
        if path.is_dir() and name.endswith("x") and name[:-1].isdigit() and int(name[:-1]) > 0:
            folders[int(name[:-1])] = path
    if not folders:
        raise DatasetError(f"{rgb} holds no rgb/<N>x image folder")
    return folders


def choose_image_folder(source: Path, resolution: int | float, full_width: int,
                        ids: list[str]) -> tuple[Path, int | float]:
    """(folder to read, resolution to apply to the images read from it), see the module docstring."""
    folders = _scale_folders(source)
    if resolution in (1, 2, 4, 8):
        if resolution in folders:
            return folders[resolution], 1
        finer = [n for n in folders if n < resolution]
        if not finer:
            raise DatasetError(f"no rgb/{resolution}x folder in {source / 'rgb'} and no finer one to derive it from")
        n = max(finer)  # factors are powers of two, so resolution / n is again 2, 4 or 8
        return folders[n], resolution // n
    if resolution == -1:
        if 2 in folders:
            log.info("hypernerf: resolution -1 reads rgb/2x (the scale 4DGS uses)")
            return folders[2], 1
        return folders[min(folders)], -1
    if resolution <= 0:
        raise DatasetError(f"resolution={resolution!r}: expected 1, 2, 4, 8, -1 or a positive width")
    widths = {}
    for n, folder in folders.items():
        probe = folder / f"{ids[0]}.png"
        widths[n] = read_rgba(probe)[0].shape[1] if probe.is_file() else full_width / n
    wide_enough = [n for n in folders if widths[n] >= resolution]
    n = max(wide_enough, key=lambda k: k) if wide_enough else min(folders)
    return folders[n], resolution


def _read_camera(path: Path, center: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, tuple[int, int], bool]:
    """(viewmat [4,4], K [3,3] at 1x, (W, H) at 1x, has_distortion) from one camera JSON."""
    data = load_json(path)
    rotation = orthonormal_rotation(json_array(data, "orientation", path, shape=(3, 3)), str(path))
    position = json_array(data, "position", path, shape=(3,))
    focal = json_float(data, "focal_length", path, positive=True)
    principal = json_array(data, "principal_point", path, shape=(2,))
    size = json_array(data, "image_size", path, shape=(2,))
    if (size < 1).any():
        raise DatasetError(f"{path}: image_size {size.tolist()} must be positive")
    aspect = json_float(data, "pixel_aspect_ratio", path, default=1.0, positive=True)
    skew = json_float(data, "skew", path, default=0.0)
    radial = json_array(data, "radial_distortion", path, default=[0.0, 0.0, 0.0])
    tangential = json_array(data, "tangential_distortion", path,
                            default=json_key(data, "tangential", path, default=[0.0, 0.0]))
    K = intrinsics(focal, focal * aspect, principal[0], principal[1], skew)
    viewmat = viewmat_from_w2c(rotation, (position - center) * scale)
    return viewmat, K, (int(size[0]), int(size[1])), bool(np.any(radial != 0) or np.any(tangential != 0))


def _splits(ids: list[str], train_ids: list, val_ids: list, source: Path) -> tuple[list[int], list[int], str]:
    if val_ids:
        index = {item: i for i, item in enumerate(ids)}
        for item in list(train_ids) + list(val_ids):
            if item not in index:
                raise DatasetError(f"{source / 'dataset.json'}: split id {item!r} is not in 'ids'")
        train_set, val_set = set(train_ids), set(val_ids)
        return ([i for i, item in enumerate(ids) if item in train_set],
                [i for i, item in enumerate(ids) if item in val_set], "vrig")
    train = [i for i in range(len(ids)) if i % 4 == 0]
    return train, [i + 2 for i in train][:-1], "interp"


def read_hypernerf(source_path: Path | str, images: str = "images", resolution: int | float = -1,
                   eval: bool = False, white_background: bool = False, llffhold: int = 8,
                   apply_scene_transform: bool = False) -> SceneInfo:
    """Read a HyperNeRF/Nerfies scene (see the module docstring); `images`, `eval`, `llffhold` unused.

    By default positions and points stay in the raw capture frame, the frame 4DGS works in (its
    hyper_loader reads scene.json's center/scale but never applies them), so a 4DGS HyperNeRF
    checkpoint can be continued; `apply_scene_transform=True` normalises as Nerfies does.
    """
    source = Path(source_path)
    dataset_path, metadata_path, scene_path = source / "dataset.json", source / "metadata.json", source / "scene.json"
    dataset, metadata, scene = load_json(dataset_path), load_json(metadata_path), load_json(scene_path)
    ids = [str(i) for i in json_key(dataset, "ids", dataset_path)]
    if not ids:
        raise DatasetError(f"{dataset_path}: 'ids' is empty")
    train_ids = [str(i) for i in json_key(dataset, "train_ids", dataset_path, default=[])]
    val_ids = [str(i) for i in json_key(dataset, "val_ids", dataset_path, default=[])]
    center = json_array(scene, "center", scene_path, shape=(3,))
    scale = json_float(scene, "scale", scene_path, positive=True)
    near = json_float(scene, "near", scene_path, default=math.nan)
    far = json_float(scene, "far", scene_path, default=math.nan) if not math.isnan(near) else math.nan
    if not apply_scene_transform:  # near/far are stated in the normalised frame
        near, far = near / scale, far / scale
        center, scale = np.zeros(3), 1.0

    time_ids, camera_ids = [], []
    for item in ids:
        entry = json_key(metadata, item, metadata_path)
        where = Path(f"{metadata_path} entry '{item}'")
        key = "time_id" if isinstance(entry, dict) and "time_id" in entry else "warp_id"
        time_ids.append(int(json_float(entry, key, where)))
        camera_ids.append(int(json_float(entry, "camera_id", where, default=0)))
    if min(time_ids) < 0:
        raise DatasetError(f"{metadata_path}: negative time/warp id")
    max_time = max(time_ids)

    cams = [_read_camera(source / "camera" / f"{item}.json", center, scale) for item in ids]
    if any(c[3] for c in cams):
        log.warning("hypernerf: cameras have lens distortion, which is ignored (as in 4DGS)")
    folder, image_resolution = choose_image_folder(source, resolution, cams[0][2][0], ids)
    point_file = find_point_file(source, POINT_FILES)
    raw_points = None if point_file is None else RawPoints.read(point_file).transformed(center, scale)

    specs = [ViewSpec(image_path=folder / f"{item}.png", image_name=item, K=K, calibrated_size=size,
                      viewmat=viewmat, time=t / max_time if max_time > 0 else 0.0, frame_index=t, camera_id=cam_id)
             for item, (viewmat, K, size, _), t, cam_id in zip(ids, cams, time_ids, camera_ids)]
    background = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    cameras = load_views(specs, image_resolution, background, same_size="camera", keep_alpha=False)
    train, test, protocol = _splits(ids, train_ids, val_ids, source)
    point_cloud = None if raw_points is None else raw_points.to_point_cloud([cameras[i] for i in train])
    has_bounds = math.isfinite(near) and math.isfinite(far) and 0 < near < far
    return assemble_scene(
        cameras, train, test, dataset_type="hypernerf", source_path=source, num_frames=len(set(time_ids)),
        point_cloud=point_cloud, near_far=(near, far) if has_bounds else None,
        metadata={"scene_center": center.astype(np.float32), "scene_scale": scale,
                  "scene_transform_applied": apply_scene_transform, "split": protocol,
                  "image_folder": str(folder.relative_to(source)),
                  "point_file": str(point_file) if point_file else None})
