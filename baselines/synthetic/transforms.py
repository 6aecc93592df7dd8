"""4x4 homogeneous transforms used by cameras and objects (float64, world frame y up)."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

# Authoring convention of the scenes: world +y is up. Cameras use OpenCV axes (x right, y down,
# z forward); look_at() builds them from this up vector.
WORLD_UP = np.array([0.0, 1.0, 0.0])


def translation(offset: Sequence[float]) -> np.ndarray:
    """[4,4] translation by a 3-vector."""
    out = np.eye(4)
    out[:3, 3] = offset
    return out


def scaling(factors: Sequence[float]) -> np.ndarray:
    """[4,4] axis-aligned scaling."""
    return np.diag([*factors, 1.0])


def rotation_euler(degrees: Sequence[float]) -> np.ndarray:
    """[4,4] rotation from extrinsic x, y, z Euler angles in degrees."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("xyz", degrees, degrees=True).as_matrix()
    return out


def rotation_axis_angle(axis: Sequence[float], degrees: float) -> np.ndarray:
    """[4,4] rotation by ``degrees`` about ``axis`` (any non-zero length)."""
    axis = np.asarray(axis, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(degrees)).as_matrix()
    return out


def rotation_vector(rotvec: Sequence[float]) -> np.ndarray:
    """[4,4] rotation from a rotation vector in radians."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()
    return out


def look_at(eye: Sequence[float], target: Sequence[float]) -> np.ndarray:
    """Camera-to-world [4,4] (OpenCV axes) of a camera at ``eye`` looking at ``target``.

    The image's up direction follows WORLD_UP; the view direction must not be vertical.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, WORLD_UP)
    norm = np.linalg.norm(right)
    if norm < 1e-6:
        raise ValueError(f"camera at {eye.tolist()} looks straight up or down; look_at undefined")
    right /= norm
    down = np.cross(forward, right)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, down, forward, eye
    return out


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """[3,3] pinhole intrinsics with horizontal field of view ``fov_deg`` and square pixels.

    The principal point is the image centre (W/2, H/2), which with pixel centres at j + 0.5 is
    the middle of the pixel grid.
    """
    focal = 0.5 * width / np.tan(np.radians(fov_deg) / 2.0)
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def c2w_to_llff(c2w: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world [4,4] -> LLFF 3x4 with rotation columns [down, right, back]."""
    return np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3]], axis=1)


def rigid_inverse(matrix: np.ndarray) -> np.ndarray:
    """Inverse of a rigid [4,4] (rotation + translation)."""
    out = np.eye(4)
    out[:3, :3] = matrix[:3, :3].T
    out[:3, 3] = -matrix[:3, :3].T @ matrix[:3, 3]
    return out
