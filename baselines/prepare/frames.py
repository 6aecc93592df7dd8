"""Stage 1: frames from a video file or a folder of images, resized and subsampled.

    frames = list_source_frames(source)            # cheap checks first (errors before long work)
    names = extract_frames(source, out_dir, width=160, fps=None, max_frames=None)

A video is anything OpenCV's `VideoCapture` opens; a folder holds JPG/PNG (and the other
formats of `IMAGE_EXTENSIONS`) images, ordered by name, all of one size. Frames are kept at a
regular stride: every k-th frame so that the rate is at most `fps` (videos only: a folder has no
frame rate), then thinned evenly to at most `max_frames`. Each kept frame is resized to `width`
(aspect ratio kept; never upscaled) and written as `images/NNNNN.png`, NNNNN being its index
in the SOURCE sequence, so names order frames in time and say where each came from.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from tqdm import tqdm

from ..data.image_io import IMAGE_EXTENSIONS, truncated_jpeg
from .errors import PrepareError


@dataclass(frozen=True)
class SourceInfo:
    """What the source holds, found without decoding every frame."""

    kind: str  # "video" | "folder"
    frame_count: int
    width: int
    height: int
    fps: float | None  # None for a folder
    files: tuple[Path, ...] = ()  # folder only, sorted by name


def _number_key(path: Path) -> list:
    """`path`'s name with its digit runs as numbers: 'f2.png' before 'f10.png'."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def require_name_order(files: Sequence[Path], what: str, option: str) -> None:
    """`PrepareError` when `files` (sorted by name) are numbered without zero padding, so that name
    order is not number order ('10.png' before '2.png'): frames would be shuffled in time, or masks
    paired with other frames."""
    by_number = sorted(files, key=_number_key)
    if list(files) != by_number:
        first = next(k for k, (a, b) in enumerate(zip(files, by_number)) if a != b)
        raise PrepareError(f"{what} {files[first].parent} are numbered without zero padding: by name "
                           f"{files[first].name} comes before {by_number[first].name}, and name order is time order",
                           f"rename them with zero-padded numbers (e.g. ffmpeg ... %05d.png), {option}")


def _probe_folder(folder: Path) -> SourceInfo:
    files = tuple(sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS))
    if not files:
        raise PrepareError(f"{folder} holds no images ({', '.join(IMAGE_EXTENSIONS)})",
                           "point at a video file or a folder of JPG/PNG frames")
    require_name_order(files, "the frames in", "or give the video itself")
    sizes: dict[tuple[int, int], Path] = {}
    for path in files:  # header-only reads would need another library; frames are small enough
        if truncated_jpeg(path):  # OpenCV would decode its missing rows as flat grey
            raise PrepareError(f"image {path} is truncated (its JPEG data ends early)", "re-copy or re-export that file")
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise PrepareError(f"cannot read image {path} (corrupt or unsupported format)",
                               "remove or re-export that file")
        sizes.setdefault((image.shape[1], image.shape[0]), path)
        if len(sizes) > 1:
            (a, pa), (b, pb) = list(sizes.items())[:2]
            raise PrepareError(f"{folder} mixes image sizes: {pa.name} is {a[0]}x{a[1]}, {pb.name} is {b[0]}x{b[1]}",
                               "give frames of one video (one camera, one size)")
    (width, height), = sizes
    return SourceInfo("folder", len(files), width, height, None, files)


def _probe_video(path: Path) -> SourceInfo:
    capture = cv2.VideoCapture(str(path))
    try:
        ok, frame = capture.read() if capture.isOpened() else (False, None)
        if not ok or frame is None:
            raise PrepareError(f"cannot read video {path} (not a video OpenCV can decode, or corrupt)",
                               "re-encode it (e.g. ffmpeg -i IN -c:v libx264 OUT.mp4) or extract its frames to a folder")
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(capture.get(cv2.CAP_PROP_FPS)) or None
        if count <= 0:  # some containers do not store it: count by demuxing (no decoding)
            count = 1
            while capture.grab():
                count += 1
    finally:
        capture.release()
    return SourceInfo("video", count, frame.shape[1], frame.shape[0], fps)


def probe_source(source: Path) -> SourceInfo:
    """Check the source and describe it; `PrepareError` for a missing, empty, unreadable or
    mixed-size source."""
    source = Path(source)
    if source.is_dir():
        return _probe_folder(source)
    if not source.exists():
        raise PrepareError(f"input not found: {source}", "give a video file or a folder of frames")
    return _probe_video(source)


def select_frames(count: int, source_fps: float | None, fps: float | None, max_frames: int | None) -> list[int]:
    """Indices of the source frames to keep (see the module docstring)."""
    stride = 1
    if fps is not None and source_fps:
        # the smallest stride whose rate is at most fps (1e-6: 30 / 10 must stay 3 after rounding)
        stride = max(1, math.ceil(source_fps / fps - 1e-6))
    indices = list(range(0, count, stride))
    if max_frames is not None and len(indices) > max_frames:
        picks = np.linspace(0, len(indices) - 1, max_frames).round().astype(int)
        indices = [indices[k] for k in picks]
    return indices


def output_size(width: int, height: int, target_width: int | None) -> tuple[int, int]:
    """(width, height) after resizing to `target_width` (aspect kept, never upscaled)."""
    if target_width is None or target_width >= width:
        return width, height
    return target_width, max(1, int(round(height * target_width / width)))


def frame_name(index: int) -> str:
    """File name of source frame `index`."""
    return f"{index:05d}.png"


def _resized(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if (image.shape[1], image.shape[0]) == size:
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _iter_video(path: Path, keep: set[int]):
    capture = cv2.VideoCapture(str(path))
    try:
        index = 0
        last = max(keep)
        while index <= last:
            ok = capture.grab()
            if not ok:
                break
            if index in keep:
                ok, frame = capture.retrieve()
                if ok:
                    yield index, frame
            index += 1
    finally:
        capture.release()


def extract_frames(source: Path, info: SourceInfo, image_dir: Path, width: int | None, fps: float | None,
                   max_frames: int | None, progress: bool = True) -> list[str]:
    """Write the kept frames to `image_dir`; returns their file names in time order."""
    indices = select_frames(info.frame_count, info.fps, fps, max_frames)
    size = output_size(info.width, info.height, width)
    image_dir.mkdir(parents=True, exist_ok=True)
    if info.kind == "folder":
        frames = ((i, cv2.imread(str(info.files[i]), cv2.IMREAD_COLOR)) for i in indices)
    else:
        frames = _iter_video(Path(source), set(indices))
    names = []
    for index, image in tqdm(frames, total=len(indices), desc="extract frames", unit="frame", disable=not progress):
        if image is None:
            raise PrepareError(f"cannot read frame {index} of {source}", "re-encode or re-export the input")
        name = frame_name(index)
        cv2.imwrite(str(image_dir / name), _resized(image, size))
        names.append(name)
    if len(names) < 2:
        raise PrepareError(f"{source} gives {len(names)} frame(s) after subsampling; SfM needs several",
                           "raise --fps / --max-frames or use a longer clip")
    return names
