"""Turning per-view metadata (paths, calibration, pose, time) into `Camera`s with pixels.

Readers first build a `ViewSpec` per image from their metadata files (cheap, fully validated),
then call `load_views`, which does the long part: decoding, compositing, resizing.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .cameras import Camera
from .errors import DatasetError
from .geometry import scale_intrinsics
from .image_io import composite, parallel_map, read_disparity, read_mask, read_rgba
from .resolution import (check_target_size, log_auto_downscale, require_scaled_copy, resize_disparity, resize_image,
                         resize_mask, size_scale, target_size)

log = logging.getLogger(__name__)


@dataclass
class ViewSpec:
    """What a reader knows about one view before its pixels are read.

    `K` [3,3] is expressed for an image of `calibrated_size` (width, height); the image on disk
    may be a scaled copy (e.g. an `images_2` folder), which `load_views` accounts for.
    """

    image_path: Path
    image_name: str
    K: np.ndarray
    calibrated_size: tuple[int, int]
    viewmat: np.ndarray
    time: float
    frame_index: int
    camera_id: int = 0
    mask_path: Path | None = None
    disparity_path: Path | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    eval_mask_path: Path | None = None  # ground-truth mask for evaluation only (extras["eval_mask"])


@dataclass
class _Loaded:
    file_size: tuple[int, int]
    image: np.ndarray
    alpha: np.ndarray | None
    K: np.ndarray
    mask: np.ndarray | None
    disparity: np.ndarray | None
    transparent: bool = False  # an RGBA image whose alpha is 0 everywhere: nothing but background
    eval_mask: np.ndarray | None = None


def _require_paths(specs: Sequence[ViewSpec]) -> None:
    """Fail before decoding anything if a file is missing."""
    for spec in specs:
        for path in (spec.image_path, spec.mask_path, spec.disparity_path, spec.eval_mask_path):
            if path is not None and not Path(path).is_file():
                raise DatasetError(f"missing file: {path}")


def load_views(specs: Sequence[ViewSpec], resolution: int | float, background: Sequence[float],
               same_size: str = "all", keep_alpha: bool = True) -> list[Camera]:
    """Decode, composite (RGBA over `background`), rescale and wrap every view as a `Camera`.

    Images are resized with INTER_AREA, masks with INTER_NEAREST, disparity with INTER_AREA
    (shrinking) or INTER_LINEAR (enlarging); masks and disparity are resized to the final image
    size whatever their stored size. `same_size` is "all" (every image must share one size) or
    "camera" (per `camera_id`). Camera uids are the positions in `specs`.
    """
    if not specs:
        raise DatasetError("no views to load")
    target_size(1000, 1000, resolution)  # rejects a bad `resolution` before any decoding
    _require_paths(specs)
    first, _ = read_rgba(specs[0].image_path)  # one decode: the size the views will have, before the rest
    check_target_size((first.shape[1], first.shape[0]), resolution, len(specs), str(Path(specs[0].image_path).parent))
    del first
    logged: set[int] = set()

    def load_one(index: int) -> _Loaded:
        spec = specs[index]
        rgb, alpha = read_rgba(spec.image_path)
        file_size = (rgb.shape[1], rgb.shape[0])
        sx, sy = size_scale(spec.calibrated_size, file_size, str(spec.image_path))
        size = target_size(*file_size, resolution)
        K = scale_intrinsics(scale_intrinsics(spec.K, sx, sy), size[0] / file_size[0], size[1] / file_size[1])
        image = resize_image(composite(rgb, alpha, background), size)
        transparent = alpha is not None and float(alpha.max()) < 1.0 / 255.0
        alpha = None if alpha is None or not keep_alpha else resize_image(alpha, size)
        mask = disparity = None
        if spec.mask_path is not None:
            mask = read_mask(spec.mask_path)
            require_scaled_copy(spec.mask_path, "motion mask", (mask.shape[1], mask.shape[0]), file_size)
            mask = resize_mask(mask, size)
        if spec.disparity_path is not None:
            disparity = read_disparity(spec.disparity_path)
            require_scaled_copy(spec.disparity_path, "disparity map", (disparity.shape[1], disparity.shape[0]), file_size)
            disparity = resize_disparity(disparity, size)
        eval_mask = None if spec.eval_mask_path is None else resize_mask(read_mask(spec.eval_mask_path), size)
        return _Loaded(file_size, image, alpha, K, mask, disparity, transparent, eval_mask)

    loaded = parallel_map(load_one, list(range(len(specs))))
    _check_sizes(specs, [item.file_size for item in loaded], same_size)
    empty = [spec.image_name for spec, item in zip(specs, loaded) if item.transparent]
    if empty:
        log.warning("%d image(s) fully transparent (alpha 0 everywhere): they train as plain background: %s%s",
                    len(empty), ", ".join(empty[:6]), " ..." if len(empty) > 6 else "")
    for item in loaded:
        if item.file_size[0] not in logged:
            log_auto_downscale(item.file_size[0], resolution)
            logged.add(item.file_size[0])

    cameras = []
    for uid, (spec, item) in enumerate(zip(specs, loaded)):
        extras = {k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in spec.extras.items()}
        if item.alpha is not None:
            extras["alpha"] = torch.from_numpy(np.ascontiguousarray(item.alpha, np.float32))
        if item.eval_mask is not None:
            extras["eval_mask"] = torch.from_numpy(item.eval_mask.astype(np.float32))
        cameras.append(Camera(
            uid=uid, image_name=spec.image_name, width=item.image.shape[1], height=item.image.shape[0],
            K=torch.from_numpy(item.K.astype(np.float32)), viewmat=torch.from_numpy(spec.viewmat.astype(np.float32)),
            time=spec.time, image=torch.from_numpy(np.ascontiguousarray(item.image, np.float32)),
            frame_index=spec.frame_index, camera_id=spec.camera_id,
            mask=None if item.mask is None else torch.from_numpy(item.mask.astype(np.float32)),
            disparity=None if item.disparity is None else torch.from_numpy(item.disparity.astype(np.float32)),
            extras=extras))
    return cameras


def _check_sizes(specs: Sequence[ViewSpec], sizes: Sequence[tuple[int, int]], same_size: str) -> None:
    first: dict[int, int] = {}
    for index, (spec, size) in enumerate(zip(specs, sizes)):
        key = 0 if same_size == "all" else spec.camera_id
        ref = first.setdefault(key, index)
        if sizes[ref] != size:
            raise DatasetError(
                f"image {spec.image_path} is {size[0]}x{size[1]} but {specs[ref].image_path} is "
                f"{sizes[ref][0]}x{sizes[ref][1]}: images of one {'dataset' if same_size == 'all' else 'camera'} "
                "must share a size")
