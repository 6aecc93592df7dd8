"""Output layout (NVIDIA/DynamicNeRF + ground truth) and crash-safe writing.

A scene is written into a hidden staging directory next to the destination and renamed into
place only when complete, so a killed run never leaves a half-written scene where a reader
looks. Files are deterministic: PNG via OpenCV (fixed compression level), .npy via numpy, JSON
in a fixed key order without timestamps.
"""
from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np


def write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same directory + os.replace)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_png(path: Path, image: np.ndarray) -> None:
    """uint8 [H,W] (grey) or [H,W,3] (RGB) -> PNG."""
    if image.ndim == 3:
        image = image[:, :, ::-1]  # OpenCV writes BGR
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image),
                               [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise RuntimeError(f"OpenCV could not encode {path}")
    write_bytes(path, encoded.tobytes())


def write_npy(path: Path, array: np.ndarray) -> None:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    write_bytes(path, buffer.getvalue())


def write_json(path: Path, data) -> None:
    write_bytes(path, (json.dumps(data, indent=1) + "\n").encode())


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8 (rounded)."""
    return np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)


def mask_png(mask: np.ndarray) -> np.ndarray:
    """Bool [H,W] -> uint8 0/255."""
    return np.where(mask, 255, 0).astype(np.uint8)


def frame_name(index: int, frames: int) -> str:
    """Zero-based frame stem: 3 digits (000, 001, ...), more only beyond 1000 frames."""
    return f"{index:0{max(3, len(str(frames - 1)))}d}"


def check_destination(out: Path) -> None:
    """Refuse to replace anything that is not an earlier simulator output (or an empty dir)."""
    if out.exists():
        if not out.is_dir():
            raise ValueError(f"output path {out} exists and is not a directory")
        if any(out.iterdir()) and not (out / "scene.json").is_file():
            raise ValueError(f"output directory {out} is not empty and holds no scene.json; "
                             f"refusing to overwrite it")


def staging_dir(out: Path) -> Path:
    """A fresh hidden directory next to ``out`` to build the scene in."""
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))


def publish(staging: Path, out: Path) -> None:
    """Move the finished staging directory to ``out``, replacing an earlier output."""
    check_destination(out)
    if out.exists():
        trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.replace(out, trash / "scene")
        os.replace(staging, out)
        shutil.rmtree(trash, ignore_errors=True)
    else:
        os.replace(staging, out)
