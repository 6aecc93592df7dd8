"""The 3DGS/4DGS `--resolution` rule and the resizing of images, masks and disparity maps."""
from __future__ import annotations

import logging
import os

import cv2
import numpy as np

from .errors import DatasetError

log = logging.getLogger(__name__)

MAX_AUTO_WIDTH = 1600


def target_size(width: int, height: int, resolution: int | float) -> tuple[int, int]:
    """(new_width, new_height) for an image of `width` x `height`, exactly as 3DGS computes it.

    `resolution` 1, 2, 4 or 8 is a downscale factor (sizes rounded); -1 keeps the original
    size unless it is wider than 1600 px, then scales it to 1600 wide; any other positive value
    is the target width (sizes truncated, as in 3DGS).
    """
    if resolution in (1, 2, 4, 8):
        return round(width / resolution), round(height / resolution)
    if resolution == -1:
        scale = width / MAX_AUTO_WIDTH if width > MAX_AUTO_WIDTH else 1.0
    elif resolution > 0:
        scale = width / float(resolution)
    else:
        raise DatasetError(f"resolution={resolution!r}: expected 1, 2, 4, 8, -1 or a positive width")
    new_w, new_h = int(width / scale), int(height / scale)
    if new_w < 1 or new_h < 1:
        raise DatasetError(f"resolution={resolution!r} gives an empty image from {width}x{height}")
    return new_w, new_h


MIN_SIDE = 4  # px: below this a view has no structure left to fit
BYTES_PER_PIXEL = 4 * 6  # float32 RGB + alpha + mask + disparity per pixel, as the loaded views hold them


def available_memory() -> int | None:
    """Bytes of memory available to new allocations (Linux MemAvailable), or None when unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_target_size(file_size: tuple[int, int], resolution: int | float, count: int, source: str,
                      memory: int | None = None) -> tuple[int, int]:
    """The size the views will have; `DatasetError` before any decoding when it is unusable.

    Unusable: a side below MIN_SIDE pixels, or `count` views of that size needing more memory than
    is available (`memory`, default: MemAvailable). Logs the size actually used.
    """
    size = target_size(*file_size, resolution)
    rule = ("a target width (3DGS's rule: -r other than 1, 2, 4, 8 is a width in pixels)"
            if resolution not in (1, 2, 4, 8, -1) else "a downscale factor")
    if min(size) < MIN_SIDE:
        raise DatasetError(f"-r/--resolution {resolution:g} makes the {file_size[0]}x{file_size[1]} images of "
                           f"{source} {size[0]}x{size[1]} px ({rule}); views need at least {MIN_SIDE} px a side")
    needed = count * size[0] * size[1] * BYTES_PER_PIXEL
    memory = available_memory() if memory is None else memory
    if memory is not None and needed > memory:
        raise DatasetError(f"-r/--resolution {resolution:g} makes the {count} images of {source} {size[0]}x{size[1]} "
                           f"px ({rule}): about {needed / 2**30:.1f} GiB to hold them, {memory / 2**30:.1f} GiB "
                           "available; choose a smaller -r")
    if size != tuple(file_size) and resolution != -1:  # -1 has its own line (log_auto_downscale)
        how = "upsampled" if size[0] > file_size[0] else "downscaled"
        log.info("views: %dx%d px, %s from %dx%d (-r %g)", size[0], size[1], how, file_size[0], file_size[1],
                 resolution)
    return size


def require_scaled_copy(path: str | os.PathLike, what: str, size: tuple[int, int], image_size: tuple[int, int],
                        tolerance_px: float = 1.5) -> None:
    """A mask or disparity map may be stored at another resolution than its image, but must be a
    scaled copy of it (same aspect, up to rounding); a transposed or cropped one is refused."""
    (w, h), (iw, ih) = size, image_size
    small_w, small_h, big_w, big_h = (w, h, iw, ih) if w * h <= iw * ih else (iw, ih, w, h)
    if abs(small_w * big_h / big_w - small_h) > tolerance_px or abs(small_h * big_w / big_h - small_w) > tolerance_px:
        raise DatasetError(f"{what} {path} is {w}x{h} but its image is {iw}x{ih}: not a scaled copy "
                           "(transposed or cropped?)")


def log_auto_downscale(width: int, resolution: int | float) -> None:
    """The one log line 3DGS prints when `resolution=-1` meets an image wider than 1600 px."""
    if resolution == -1 and width > MAX_AUTO_WIDTH:
        log.info("input images are %d px wide (> %d): rescaling to %d px wide; pass resolution=1 "
                 "to keep the original size", width, MAX_AUTO_WIDTH, MAX_AUTO_WIDTH)


def resize_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """[H,W,C] or [H,W] float image resized to (w, h) with area averaging (anti-aliased)."""
    if (image.shape[1], image.shape[0]) == tuple(size):
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Binary [H,W] mask resized to (w, h) with nearest neighbour (stays binary)."""
    if (mask.shape[1], mask.shape[0]) == tuple(size):
        return mask
    return cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)


def resize_disparity(disparity: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """[H,W] disparity resized to (w, h): area averaging when shrinking, bilinear when enlarging.

    Values are not rescaled: disparity is a per-pixel quantity (1/depth), independent of size.
    """
    if (disparity.shape[1], disparity.shape[0]) == tuple(size):
        return disparity
    shrinking = size[0] <= disparity.shape[1] and size[1] <= disparity.shape[0]
    return cv2.resize(disparity, size, interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)


def size_scale(from_size: tuple[int, int], to_size: tuple[int, int], source: str,
               tolerance_px: float = 1.5) -> tuple[float, float]:
    """(sx, sy) = to / from per axis, checking that both axes describe the same scaling.

    Downscaled copies round (or truncate) each side separately, so predicting one side from the
    other's scale may miss by about a pixel; more means the image does not belong to these
    intrinsics (e.g. a crop, or another camera's image).
    """
    (fw, fh), (tw, th) = from_size, to_size
    sx, sy = tw / fw, th / fh
    if max(abs(sx * fh - th), abs(sy * fw - tw)) > tolerance_px:
        raise DatasetError(f"{source}: image size {tw}x{th} is not a scaled copy of the "
                           f"calibrated size {fw}x{fh}")
    return sx, sy
