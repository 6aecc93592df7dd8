"""Camera conventions: conversions into world->camera OpenCV matrices and pinhole intrinsics.

Our convention: `viewmat` [4,4] world->camera with camera axes x right, y down, z forward;
`K` [3,3] in pixels with the centre of pixel (row i, col j) at (x=j+0.5, y=i+0.5).
"""
from __future__ import annotations

import numpy as np

from .errors import DatasetError

# Column permutation from LLFF's camera-to-world columns [down, right, back] to OpenCV's
# [right, down, forward]: x = right = col 1, y = down = col 0, z = forward = -back = -col 2.
_LLFF_TO_OPENCV = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# OpenGL/Blender camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward).
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


def orthonormal_rotation(R: np.ndarray, source: str, tol: float = 1e-2) -> np.ndarray:
    """Nearest proper rotation to `R` [3,3] (SVD); `DatasetError` if `R` is far from one.

    Files store rotations in limited precision, so small deviations are projected away; a
    reflection or a badly non-orthogonal matrix means a corrupt or misread pose.
    """
    U, _, Vt = np.linalg.svd(R)
    nearest = U @ Vt
    if np.linalg.det(nearest) < 0 or np.abs(nearest - R).max() > tol:
        raise DatasetError(f"{source}: not a rotation matrix (det {np.linalg.det(R):.4f}):\n{R}")
    return nearest


def viewmat_from_c2w(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """World->camera [4,4] from a camera-to-world rotation [3,3] (OpenCV axes) and centre [3]."""
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3] = -rotation.T @ centre
    return viewmat


def viewmat_from_w2c(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """World->camera [4,4] from a world-to-camera rotation [3,3] (OpenCV axes) and centre [3]."""
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ centre
    return viewmat


def llff_c2w_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """LLFF camera-to-world rotation [3,3] (columns down, right, back) -> OpenCV axes."""
    return c2w @ _LLFF_TO_OPENCV


def opencv_c2w_to_llff(c2w: np.ndarray) -> np.ndarray:
    """Inverse of `llff_c2w_to_opencv` (the permutation is its own inverse)."""
    return c2w @ _LLFF_TO_OPENCV


def opengl_c2w_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation [3,3] with OpenGL/Blender axes -> OpenCV axes (also the inverse)."""
    return c2w @ _OPENGL_TO_OPENCV


def intrinsics(fx: float, fy: float, cx: float, cy: float, skew: float = 0.0) -> np.ndarray:
    """Pinhole K [3,3] in pixels (principal point in our +0.5 pixel-centre convention)."""
    return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def scale_intrinsics(K: np.ndarray, scale_x: float, scale_y: float) -> np.ndarray:
    """K for an image resized by (scale_x, scale_y) = (new_w / old_w, new_h / old_h).

    With pixel centres at +0.5 the continuous image coordinate scales linearly (the image
    corners map to the corners), so fx, skew, cx scale by scale_x and fy, cy by scale_y.
    """
    return np.diag([scale_x, scale_y, 1.0]) @ K


def focal_from_fov(fov: float, size: float) -> float:
    return 0.5 * size / np.tan(0.5 * fov)


def camera_centre(viewmat: np.ndarray) -> np.ndarray:
    """Camera centre [3] in world coordinates from a world->camera [4,4]."""
    return -viewmat[:3, :3].T @ viewmat[:3, 3]
