"""CMU Panoptic captures in the Dynamic3DGaussians layout, read with the monocular protocol.

    <scene>/train_meta.json, test_meta.json:
        {"w": W, "h": H,
         "k":      [T][C] 3x3 intrinsics (pixel centres at integers, OpenCV calibration),
         "w2c":    [T][C] 4x4 world->camera, OpenCV axes,
         "fn":     [T][C] image path relative to ims/, e.g. "1/000000.jpg",
         "cam_id": [T][C] rig camera id}
    <scene>/ims/<cam>/<frame>.jpg     every camera's video
    <scene>/seg/<cam>/<frame>.png     optional person masks (255 = person), evaluation only
    <scene>/points3D.ply              optional point cloud; none is stored for the basketball
                                      capture, and `triangulate_first_timestep` (run by the
                                      benchmark's --setup) writes one from all train_meta cameras
                                      at timestamp 0 (without it, `initial_points.py` triangulates
                                      from the training views)

Monocular protocol (as NVIDIA Dynamic Scenes): timestamp t trains on ONE view, camera
`train_cameras[t % len(train_cameras)]` of train_meta.json, so the cameras cycle over a small set
of neighbouring rig cameras (consecutive frames stay a small baseline apart, as in a hand-held
video, which optical flow between them needs). Default (`train_cameras=None`): the
`CLUSTER_SIZE` training cameras nearest to the first test camera, ordered along the cluster's
longest axis (basketball: test camera 0 and training cameras 17, 29, 13, 21, 24). With `eval`,
the test cameras (`test_cameras`, default: that first test camera only; the others face the
scene from sides the cluster never sees) are test views at every `test_every`-th timestamp
(0, k, 2k, ...); these are true novel views: no training image comes from those cameras.

Masks: `seg/` gives people masks for the training cameras. They are the evaluation's dynamic
masks (`extras["eval_mask"]`); training never sees them unless `train_masks=True` (then they are
`Camera.mask`). The test cameras have no `seg/` in this layout: their evaluation mask is the
people's visual hull, carved at that timestamp from the seg masks of ALL training-meta cameras
(`visual_hull_masks`), so "PSNR inside the masks" scores the people on the held-out views.

Times are t / (T - 1). Pixel centres move from integers to +0.5 (our convention, geometry.py).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import DatasetError
from .geometry import orthonormal_rotation
from .image_io import read_mask
from .nvidia import find_point_file
from .pointcloud import RawPoints
from .scene_info import SceneInfo, assemble_scene
from .validation import json_key, load_json, require_finite
from .views import ViewSpec, load_views

log = logging.getLogger(__name__)

TRAIN_FILE, TEST_FILE = "train_meta.json", "test_meta.json"
POINT_FILES = ("points3D.ply", "points3d.ply", "pointd3D.ply")
PER_VIEW_KEYS = ("k", "w2c", "fn", "cam_id")


class Meta:
    """One validated meta file: intrinsics [T,C,3,3], w2c [T,C,4,4], file names [T][C], ids [T][C]."""

    def __init__(self, path: Path):
        data = load_json(path)
        self.path = path
        self.width = _positive_int(json_key(data, "w", path), "w", path)
        self.height = _positive_int(json_key(data, "h", path), "h", path)
        lists = {key: json_key(data, key, path) for key in PER_VIEW_KEYS}
        for key, value in lists.items():
            if not isinstance(value, list) or not value or not all(isinstance(row, list) for row in value):
                raise DatasetError(f"{path}: '{key}' must be a non-empty list (timestamps) of lists (cameras)")
        steps = {key: len(value) for key, value in lists.items()}
        if len(set(steps.values())) != 1:
            raise DatasetError(f"{path}: per-timestamp lists differ in length: {steps}")
        self.num_steps = steps["fn"]
        self.num_cameras = len(lists["fn"][0])
        for key, value in lists.items():
            for t, row in enumerate(value):
                if len(row) != self.num_cameras:
                    raise DatasetError(f"{path}: '{key}'[{t}] has {len(row)} cameras, 'fn'[0] has "
                                       f"{self.num_cameras}")
        self.K = _array(lists["k"], (3, 3), "k", path)
        self.w2c = _array(lists["w2c"], (4, 4), "w2c", path)
        for t in range(self.num_steps):
            for c in range(self.num_cameras):
                orthonormal_rotation(self.w2c[t, c, :3, :3], f"{path} w2c[{t}][{c}]")
                if self.K[t, c, 0, 0] <= 0 or self.K[t, c, 1, 1] <= 0:
                    raise DatasetError(f"{path}: k[{t}][{c}] has a non-positive focal length")
        self.fn = [[str(name) for name in row] for row in lists["fn"]]
        try:
            self.cam_id = [[int(cid) for cid in row] for row in lists["cam_id"]]
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"{path}: 'cam_id' holds a non-integer: {exc}") from None
        if len(set(self.cam_id[0])) != self.num_cameras:
            raise DatasetError(f"{path}: 'cam_id'[0] repeats a camera: {self.cam_id[0]}")
        moved = next((t for t, row in enumerate(self.cam_id) if row != self.cam_id[0]), None)
        if moved is not None:  # columns index cameras at every timestamp
            raise DatasetError(f"{path}: 'cam_id'[{moved}] lists the cameras in another order than 'cam_id'[0]")

    def column(self, camera_id: int) -> int:
        """The camera's position in the per-timestamp lists (it is the same at every timestamp)."""
        return self.cam_id[0].index(camera_id)

    def centres(self) -> np.ndarray:
        """[C,3] camera centres at the first timestamp."""
        R, t = self.w2c[0, :, :3, :3], self.w2c[0, :, :3, 3]
        return -np.einsum("cji,cj->ci", R, t)


def _positive_int(value, key: str, path: Path) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 1 or int(value) != value:
        raise DatasetError(f"{path}: '{key}' must be a positive integer, got {value!r}")
    return int(value)


def _array(value: list, shape: tuple[int, int], key: str, path: Path) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: '{key}' is not a [T][C]{list(shape)} numeric array") from None
    if array.shape[2:] != shape:
        raise DatasetError(f"{path}: '{key}' entries have shape {array.shape[2:]}, expected {shape}")
    return require_finite(array, path, f"'{key}' value")


CLUSTER_SIZE = 5


def default_train_cameras(train: Meta, test: Meta, size: int = CLUSTER_SIZE) -> list[int]:
    """The `size` training cameras nearest to the first test camera, ordered along the cluster's
    longest axis (a smooth sweep, like a rig's cameras left to right)."""
    train_centres = train.centres()
    nearest = np.argsort(np.linalg.norm(train_centres - test.centres()[0], axis=1), kind="stable")[:size]
    cluster = train_centres[nearest]
    offsets = cluster - cluster.mean(axis=0)
    axis = np.linalg.svd(offsets, full_matrices=False)[2][0] if len(cluster) > 1 else np.zeros(3)
    axis = axis if axis[np.argmax(np.abs(axis))] > 0 else -axis  # a fixed sign: the order is repeatable
    order = np.argsort(offsets @ axis, kind="stable")
    return [train.cam_id[0][i] for i in nearest[order]]


def _parse_ids(chosen: Sequence[int] | str, option: str) -> list[int]:
    if isinstance(chosen, str):
        try:
            return [int(part) for part in chosen.split(",") if part.strip()]
        except ValueError:
            raise DatasetError(f"{option}={chosen!r}: expected camera ids like 1,2,3") from None
    return [int(c) for c in chosen]


def _resolve_cameras(meta: Meta, chosen: Sequence[int] | str | None, option: str) -> list[int] | None:
    """The ids named in `chosen` (checked against `meta`), or None when nothing is named."""
    if chosen is None or chosen == "" or chosen == []:
        return None
    cameras = _parse_ids(chosen, option)
    unknown = [c for c in cameras if c not in meta.cam_id[0]]
    if unknown or not cameras:
        raise DatasetError(f"{option} {unknown or cameras} are not cameras of {meta.path} "
                           f"(it has {meta.cam_id[0]})")
    return cameras


def visual_hull_masks(seg_masks: Sequence[np.ndarray], K: np.ndarray, w2c: np.ndarray, targets_K: np.ndarray,
                      targets_w2c: np.ndarray, size: tuple[int, int], box: np.ndarray, voxels: int = 96,
                      min_views: int = 3, slack: int = 1) -> np.ndarray:
    """Masks of the silhouettes' visual hull seen from target cameras.

    Args:
        seg_masks: C [H,W] bool silhouettes, one per carving camera.
        K, w2c: [C,3,3] / [C,4,4] carving cameras (pixel centres at +0.5).
        targets_K, targets_w2c: [V,3,3] / [V,4,4] cameras to render the hull into.
        size: (width, height) of every image.
        box: [2,3] world box carved (min, max).
        voxels: grid cells along the box's longest side.
        min_views: a voxel must project inside at least this many carving images.
        slack: carving cameras whose silhouette may miss a voxel (segmentation holes).
    Returns: [V,H,W] bool masks (the hull's voxels splatted at their projected size).
    """
    width, height = size
    extent = box[1] - box[0]
    step = float(extent.max()) / voxels
    axes = [np.arange(box[0][i] + step / 2, box[1][i], step) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    seen = np.zeros(len(grid), np.int32)
    misses = np.zeros(len(grid), np.int32)
    for mask, k, v in zip(seg_masks, K, w2c):
        x, y, ok = _project(grid, k, v, width, height)
        seen += ok
        misses += ok & ~mask[y, x]
        keep = misses <= slack  # carved away for good: most of the box goes after a few cameras
        grid, seen, misses = grid[keep], seen[keep], misses[keep]
    hull = grid[seen >= min_views]
    out = np.zeros((len(targets_K), height, width), bool)
    for i, (k, v) in enumerate(zip(targets_K, targets_w2c)):
        cam = hull @ v[:3, :3].T + v[:3, 3]
        x, y, ok = _project(hull, k, v, width, height)
        radius = np.ceil(k[0, 0] * step / np.maximum(cam[:, 2], 1e-6) / 2).astype(int)
        for r in np.unique(radius[ok]):
            pick = ok & (radius == r)
            layer = np.zeros((height, width), np.uint8)
            layer[y[pick], x[pick]] = 1
            out[i] |= _dilate(layer, int(r)) > 0
    return out


def _project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int):
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    safe = np.where(z > 1e-6, z, 1.0)
    x = np.floor(K[0, 0] * cam[:, 0] / safe + K[0, 1] * cam[:, 1] / safe + K[0, 2]).astype(np.int64)
    y = np.floor(K[1, 1] * cam[:, 1] / safe + K[1, 2]).astype(np.int64)
    ok = (z > 1e-6) & (x >= 0) & (x < width) & (y >= 0) & (y < height)
    return np.clip(x, 0, width - 1), np.clip(y, 0, height - 1), ok


def _dilate(layer: np.ndarray, radius: int) -> np.ndarray:
    import cv2

    if radius <= 0:
        return layer
    return cv2.dilate(layer, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1)))


def _hull_box(meta: Meta) -> np.ndarray:
    """[2,3] box carved for the hull: the cameras' box (they ring the scene) grown on every side by a
    quarter of its largest size, since the floor lies below the lowest camera."""
    centres = meta.centres()
    low, high = centres.min(axis=0), centres.max(axis=0)
    margin = 0.25 * float((high - low).max())
    return np.stack([low - margin, high + margin])


def triangulate_first_timestep(source_path: Path | str, out_file: Path | str, seed: int = 0,
                               num_threads: int = 1) -> int:
    """Write `out_file` (PLY: x, y, z, red, green, blue) with static points triangulated by pycolmap
    from every train_meta.json camera at timestamp 0, poses and intrinsics fixed, features masked
    out inside seg/ (the people). Returns the number of points; `DatasetError` under 100.

    `num_threads` 1 keeps the point set repeatable (COLMAP's multi-threaded RANSAC is not: 169 vs 167
    points seen with 2 threads on basketball). Uses cameras the monocular protocol does not train on: the static background only, as the
    dataset's own point file would be (Dynamic3DGaussians ships one built from all cameras).
    """
    from plyfile import PlyData, PlyElement

    from .cameras import Camera
    from .image_io import read_rgba
    from .triangulation import triangulate_static_points

    source = Path(source_path)
    meta = Meta(source / TRAIN_FILE)
    shift = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    cameras = []
    for c in range(meta.num_cameras):
        rgb, _ = read_rgba(source / "ims" / meta.fn[0][c])
        seg = source / "seg" / Path(meta.fn[0][c]).with_suffix(".png")
        cameras.append(Camera(uid=c, image_name=f"cam{meta.cam_id[0][c]:02d}", width=rgb.shape[1], height=rgb.shape[0],
                              K=meta.K[0, c] + shift, viewmat=meta.w2c[0, c], time=0.0, image=rgb,
                              camera_id=meta.cam_id[0][c], mask=read_mask(seg) if seg.is_file() else None))
    result = triangulate_static_points(cameras, max_images=len(cameras), exhaustive_up_to=len(cameras),
                                       seed=seed, num_threads=num_threads)
    if len(result) < 100:
        raise DatasetError(f"{source}: only {len(result)} points triangulated from {len(cameras)} cameras at timestamp 0")
    vertex = np.empty(len(result), dtype=[(k, "f4") for k in "xyz"] + [(k, "u1") for k in ("red", "green", "blue")])
    for i, k in enumerate("xyz"):
        vertex[k] = result.points[:, i]
    colours = np.clip(np.round(result.colors * 255), 0, 255).astype(np.uint8)
    for i, k in enumerate(("red", "green", "blue")):
        vertex[k] = colours[:, i]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(out_file))
    return len(result)


def read_panoptic(source_path: Path | str, images: str = "ims", resolution: int | float = -1,
                  eval: bool = False, white_background: bool = False, llffhold: int = 8,
                  train_cameras: Sequence[int] | str | None = None, test_cameras: Sequence[int] | str | None = None,
                  test_every: int = 10, train_masks: bool = False, hull_voxels: int = 96) -> SceneInfo:
    """Read a Dynamic3DGaussians-layout capture with the monocular protocol (module docstring).

    Args:
        images: unused (the layout's image folder is ims/); llffhold unused (see test_every).
        train_cameras: rig camera ids cycled over the timestamps (list or "1,2,3"); None = default.
        test_cameras: test_meta.json camera ids held out with `eval`; None = the first one.
        test_every: with `eval`, test views at timestamps 0, k, 2k, ... (k = test_every).
        train_masks: give training the seg/ masks as `Camera.mask` (by default evaluation only).
        hull_voxels: grid resolution of the test cameras' visual-hull masks.
    """
    source = Path(source_path)
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 1:
        raise DatasetError(f"test_every={test_every!r}: must be a positive integer")
    train_meta = Meta(source / TRAIN_FILE)
    test_meta = Meta(source / TEST_FILE) if (eval or (source / TEST_FILE).is_file()) else None
    if test_meta is not None:
        for key in ("width", "height", "num_steps"):
            if getattr(test_meta, key) != getattr(train_meta, key):
                raise DatasetError(f"{test_meta.path}: {key} {getattr(test_meta, key)} differs from "
                                   f"{train_meta.path}'s {getattr(train_meta, key)}")
    cycle = _resolve_cameras(train_meta, train_cameras, "train_cameras")
    if cycle is None:
        if test_meta is None:
            raise DatasetError(f"{source / TEST_FILE} is needed to choose the default training cameras "
                               "(or name them: --train_cameras 1,2,3)")
        cycle = default_train_cameras(train_meta, test_meta)
    held_out = None
    if eval:
        held_out = _resolve_cameras(test_meta, test_cameras, "test_cameras") or test_meta.cam_id[0][:1]
    steps = train_meta.num_steps
    point_file = find_point_file(source, POINT_FILES)
    raw_points = None if point_file is None else RawPoints.read(point_file)
    pixel_shift = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # integer pixel centres -> +0.5
    seg_root = source / "seg"

    def spec(meta: Meta, t: int, column: int, with_seg: bool) -> ViewSpec:
        name = meta.fn[t][column]
        seg = seg_root / Path(name).with_suffix(".png") if with_seg else None
        camera_id = meta.cam_id[t][column]
        return ViewSpec(image_path=source / "ims" / name, image_name=f"cam{camera_id:02d}_{t:06d}",
                        K=meta.K[t, column] + pixel_shift, calibrated_size=(meta.width, meta.height),
                        viewmat=meta.w2c[t, column], time=t / (steps - 1) if steps > 1 else 0.0,
                        frame_index=t, camera_id=camera_id,
                        mask_path=seg if train_masks else None, eval_mask_path=None if train_masks else seg)

    has_seg = seg_root.is_dir()
    if train_masks and not has_seg:
        raise DatasetError(f"train_masks=True but {seg_root} does not exist")
    specs = [spec(train_meta, t, train_meta.column(cycle[t % len(cycle)]), has_seg) for t in range(steps)]
    test_steps = list(range(0, steps, test_every)) if eval else []
    if eval:
        specs += [spec(test_meta, t, test_meta.column(c), False) for t in test_steps for c in held_out]
    background = (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)
    cameras = load_views(specs, resolution, background, same_size="all")
    train = list(range(steps))
    test = list(range(steps, len(cameras)))
    if eval and has_seg:
        _add_hull_masks(cameras[steps:], train_meta, test_meta, held_out, test_steps, source, hull_voxels)
    point_cloud = None if raw_points is None else raw_points.to_point_cloud([cameras[i] for i in train])
    # what the run trained and tested on (train.py records it in config.json as "_protocol")
    protocol = {"train_cameras": cycle, "test_cameras": held_out or [], "test_every": test_every,
                "test_timestamps": test_steps, "train_masks": train_masks,
                "test_masks": "visual hull of seg/" if eval and has_seg else None}
    log.info("panoptic monocular protocol: timestamp t trains on camera %s[t %% %d]; test cameras %s at %d timestamps",
             cycle, len(cycle), protocol["test_cameras"], len(test_steps))
    return assemble_scene(cameras, train, test, dataset_type="panoptic", source_path=source, num_frames=steps,
                          point_cloud=point_cloud,
                          metadata={"protocol": protocol, "point_file": str(point_file) if point_file else None})


def _add_hull_masks(test_cameras: list, train_meta: Meta, test_meta: Meta, held_out: list[int],
                    test_steps: list[int], source: Path, voxels: int) -> None:
    """Set extras["eval_mask"] of the test views (test order: timestamp-major) from the seg/ hull."""
    import cv2
    import torch

    width, height = test_cameras[0].width, test_cameras[0].height
    box = _hull_box(train_meta)
    shift = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    columns = [test_meta.column(c) for c in held_out]
    per_step = len(columns)
    for n, t in enumerate(test_steps):
        segs, Ks, w2cs = [], [], []
        for c in range(train_meta.num_cameras):
            path = source / "seg" / Path(train_meta.fn[t][c]).with_suffix(".png")
            if not path.is_file():
                continue
            mask = read_mask(path)
            if mask.shape != (train_meta.height, train_meta.width):
                raise DatasetError(f"{path} is {mask.shape[1]}x{mask.shape[0]}, expected "
                                   f"{train_meta.width}x{train_meta.height}")
            segs.append(mask > 0.5)
            Ks.append(train_meta.K[t, c] + shift)
            w2cs.append(train_meta.w2c[t, c])
        if len(segs) < 3:
            raise DatasetError(f"{source / 'seg'}: only {len(segs)} training cameras have masks at timestamp {t}; "
                               "the test views' hull needs 3 or more")
        hull = visual_hull_masks(segs, np.stack(Ks), np.stack(w2cs),
                                 np.stack([test_meta.K[t, c] + shift for c in columns]),
                                 test_meta.w2c[t, columns], (train_meta.width, train_meta.height), box, voxels=voxels)
        for c in range(per_step):
            mask = hull[c].astype(np.uint8)
            if (width, height) != (train_meta.width, train_meta.height):  # carved at the stored size
                mask = cv2.resize(mask, (width, height), interpolation=cv2.INTER_NEAREST)
            test_cameras[n * per_step + c].extras["eval_mask"] = torch.from_numpy(mask.astype(np.float32))
