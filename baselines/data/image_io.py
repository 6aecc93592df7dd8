"""Reading images, motion masks and disparity maps with OpenCV, each failure naming its file."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Sequence, TypeVar

import cv2
import numpy as np

from .errors import DatasetError
from .validation import load_npy, require_finite

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr", ".webp")
T = TypeVar("T")


def list_files(folder: Path, extensions: Sequence[str]) -> list[Path]:
    """Files of `folder` with one of `extensions` (case-insensitive), sorted by name."""
    if not folder.is_dir():
        raise DatasetError(f"missing folder: {folder}")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in extensions)


def truncated_jpeg(path: Path) -> bool:
    """True if `path` is a JPEG whose data ends before its end marker (a copy or write cut short).

    OpenCV decodes such a file without an error (libjpeg only prints "Premature end of JPEG
    file") and fills the missing rows with flat grey, which would train as real pixels. Pillow
    (installed with scikit-image and matplotlib) raises instead; it decodes at 1/8 scale here,
    which still reads every byte of the compressed data. Other formats, and files Pillow cannot
    open, give False: OpenCV's own decode judges them.
    """
    from PIL import Image

    try:
        with Image.open(path) as image:
            if image.format != "JPEG":
                return False
            image.draft(image.mode, (max(1, image.width // 8), max(1, image.height // 8)))
            image.load()
    except OSError as err:
        return "truncated" in str(err)
    except Exception:  # noqa: BLE001 - Pillow's decoders raise assorted errors; OpenCV has the last word
        return False
    return False


def read_rgba(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(rgb [H,W,3] float32 in [0,1], alpha [H,W] float32 or None) from an 8/16-bit or float image."""
    if truncated_jpeg(path):  # before OpenCV, which would print libjpeg's warning and decode grey rows
        raise DatasetError(f"image {path} is truncated (its JPEG data ends early; re-copy or re-export it)")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise DatasetError(f"cannot read image {path} (missing, corrupt or unsupported format)")
    if data.dtype == np.uint8:
        data = data.astype(np.float32) / 255.0
    elif data.dtype == np.uint16:
        data = data.astype(np.float32) / 65535.0
    else:
        data = data.astype(np.float32)
    if data.ndim == 2:
        data = data[..., None]
    channels = data.shape[2]
    if channels == 1:
        return np.repeat(data, 3, axis=2), None
    if channels == 3:
        return np.ascontiguousarray(data[..., ::-1]), None
    if channels == 4:
        return np.ascontiguousarray(data[..., 2::-1]), np.ascontiguousarray(data[..., 3])
    raise DatasetError(f"image {path} has {channels} channels (expected 1, 3 or 4)")


def composite(rgb: np.ndarray, alpha: np.ndarray | None, background: Sequence[float]) -> np.ndarray:
    """rgb * alpha + background * (1 - alpha) (rgb unchanged when there is no alpha)."""
    if alpha is None:
        return rgb
    a = alpha[..., None]
    return rgb * a + np.asarray(background, np.float32) * (1.0 - a)


def read_mask(path: Path) -> np.ndarray:
    """[H,W] float32 binary mask, 1 where the stored value is above half range (255 = dynamic)."""
    if truncated_jpeg(path):  # before OpenCV, which would print libjpeg's warning and decode grey rows
        raise DatasetError(f"mask {path} is truncated (its JPEG data ends early; re-copy or re-export it)")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise DatasetError(f"cannot read mask {path} (missing, corrupt or unsupported format)")
    if data.ndim == 3:
        data = data[..., :3].max(axis=2)
    half = 127 if data.dtype == np.uint8 else (32767 if data.dtype == np.uint16 else 0.5)
    return (data > half).astype(np.float32)


def read_disparity(path: Path) -> np.ndarray:
    """[H,W] float32 disparity from an .npy of shape [H,W] or [H,W,1]; must be finite."""
    array = load_npy(path)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    if array.ndim != 2 or 0 in array.shape:
        raise DatasetError(f"disparity {path} has shape {array.shape}, expected [H, W]")
    require_finite(array, path, "disparity")
    return array.astype(np.float32)


def parallel_map(fn: Callable[[Path], T], paths: Sequence[Path]) -> list[T]:
    """`[fn(p) for p in paths]` on a thread pool (OpenCV decoding releases the GIL).

    The first failure is re-raised as is, so a `DatasetError` still names its file.
    """
    workers = max(1, min(8, os.cpu_count() or 1, len(paths)))
    if workers == 1:
        return [fn(p) for p in paths]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(fn, paths))


def check_same_size(paths: Sequence[Path], arrays: Sequence[np.ndarray], what: str) -> tuple[int, int]:
    """(width, height) shared by all arrays; `DatasetError` naming the first file that differs."""
    h, w = arrays[0].shape[:2]
    for path, array in zip(paths, arrays):
        if array.shape[:2] != (h, w):
            raise DatasetError(f"{what} {path} is {array.shape[1]}x{array.shape[0]} but {paths[0]} is {w}x{h}: "
                               "all must have the same size")
    return w, h
