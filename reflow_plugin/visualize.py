"""Pictures of flow: the standard colour wheel and the flow-matching panels.

    rgb = flow_to_color(flow, max_magnitude=None)      # [H, W, 3] uint8 (hue = direction, saturation = speed)
    write_panel(path, I_a, I_b_warped, I_b, valid, flow)

The colour wheel is the Middlebury one (Baker et al., IJCV 2011): 55 hues built from six
segments (red-yellow-green-cyan-blue-magenta), white at zero motion, full colour at the largest
magnitude. Panels are [I_a | I_b warped to a | I_b | |I_a - warp| | flow], the paper's "flow
matching progress" figure with the error and the flow added; invalid pixels are shown black.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

_SEGMENTS = ((15, (255, 0, 0), (255, 255, 0)), (6, (255, 255, 0), (0, 255, 0)), (4, (0, 255, 0), (0, 255, 255)),
             (11, (0, 255, 255), (0, 0, 255)), (13, (0, 0, 255), (255, 0, 255)), (6, (255, 0, 255), (255, 0, 0)))


def color_wheel() -> np.ndarray:
    """[55, 3] float RGB in [0, 1] around the Middlebury colour wheel."""
    colours = []
    for count, start, end in _SEGMENTS:
        t = np.arange(count)[:, None] / count
        colours.append((1 - t) * np.asarray(start, float) + t * np.asarray(end, float))
    return np.concatenate(colours) / 255.0


def flow_to_color(flow: np.ndarray, max_magnitude: float | None = None, valid: np.ndarray | None = None) -> np.ndarray:
    """[H, W, 3] uint8 RGB of a flow [H, W, 2]; `max_magnitude` saturates (default: the largest)."""
    flow = np.nan_to_num(np.asarray(flow, np.float64))
    u, v = flow[..., 0], flow[..., 1]
    magnitude = np.sqrt(u * u + v * v)
    scale = max_magnitude if max_magnitude else float(magnitude.max() if magnitude.size else 0.0)
    radius = np.clip(magnitude / max(scale, 1e-9), 0.0, 1.0)
    wheel = color_wheel()
    angle = np.arctan2(-v, -u) / np.pi  # [-1, 1]
    position = (angle + 1.0) / 2.0 * (len(wheel) - 1)
    k0 = np.floor(position).astype(int)
    k1 = (k0 + 1) % len(wheel)
    f = (position - k0)[..., None]
    colour = (1 - f) * wheel[k0] + f * wheel[k1]
    colour = 1.0 - radius[..., None] * (1.0 - colour)  # white at rest, saturated when fast
    if valid is not None:
        colour[~np.asarray(valid, bool)] = 0.0
    return (colour * 255.0 + 0.5).astype(np.uint8)


def _rgb_u8(image: np.ndarray) -> np.ndarray:
    return (np.clip(np.asarray(image, np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def panel(image_a: np.ndarray, warped: np.ndarray, image_b: np.ndarray, valid: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """[H, 5W, 3] uint8 RGB: I_a | I_b warped | I_b | |error| (x4, masked) | flow colours."""
    valid = np.asarray(valid, bool)
    error = np.abs(np.asarray(warped) - np.asarray(image_a)).mean(-1, keepdims=True).repeat(3, -1) * 4.0
    error[~valid] = 0.0
    warped_shown = np.where(valid[..., None], warped, 0.0)
    return np.concatenate([_rgb_u8(image_a), _rgb_u8(warped_shown), _rgb_u8(image_b), _rgb_u8(error),
                           flow_to_color(flow, valid=valid)], axis=1)


def write_panel(path: Path, image_a: np.ndarray, warped: np.ndarray, image_b: np.ndarray, valid: np.ndarray,
                flow: np.ndarray) -> Path:
    """Write `panel(...)` as a PNG (parent folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(panel(image_a, warped, image_b, valid, flow), cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
    return path
