"""Camera conversions between the browser (viser) and the project's conventions.

viser reports a client's camera as a pose (wxyz, position) with OpenCV axes (x right, y down,
z forward: `P_world = R p_camera + position`), the canvas aspect and a vertical field of view;
the project's rasterizer wants a world-to-camera `viewmat` [4, 4] and intrinsics `K` [3, 3] in
pixels with pixel centres at +0.5. Both use OpenCV axes, so no axis flip is involved.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import viser.transforms as vt
from torch import Tensor


def view_from_pose(wxyz: np.ndarray, position: np.ndarray) -> Tensor:
    """[4, 4] float32 world-to-camera matrix of a camera pose (quaternion w, x, y, z; centre)."""
    c2w = np.eye(4)
    c2w[:3, :3] = vt.SO3(np.asarray(wxyz, np.float64)).as_matrix()
    c2w[:3, 3] = np.asarray(position, np.float64)
    return torch.from_numpy(np.linalg.inv(c2w).astype(np.float32))


def pose_from_view(viewmat: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz [4], position [3]) of a world-to-camera matrix (the inverse of `view_from_pose`)."""
    c2w = np.linalg.inv(viewmat.detach().cpu().double().numpy())
    return vt.SO3.from_matrix(c2w[:3, :3]).wxyz, c2w[:3, 3]


def intrinsics(fov_y: float, width: int, height: int) -> Tensor:
    """[3, 3] K of a pinhole camera with vertical field of view `fov_y` (radians), centred."""
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    return torch.tensor([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float32)


def vertical_fov(K: Tensor, height: int) -> float:
    """Vertical field of view (radians) of intrinsics K for an image `height` pixels tall."""
    return 2.0 * math.atan(0.5 * height / float(K[1, 1]))


def image_size(aspect: float, max_side: int) -> tuple[int, int]:
    """(width, height) with the given aspect whose longer side is `max_side` (at least 8 px each)."""
    if aspect >= 1.0:
        width, height = max_side, max_side / aspect
    else:
        width, height = max_side * aspect, max_side
    return max(8, int(round(width))), max(8, int(round(height)))


def scene_up(viewmats: list[Tensor]) -> np.ndarray:
    """World up direction of a capture: minus the mean camera y axis (OpenCV y points down)."""
    down = np.mean([np.linalg.inv(v.detach().cpu().double().numpy())[:3, 1] for v in viewmats], axis=0)
    norm = float(np.linalg.norm(down))
    return -down / norm if norm > 1e-9 else np.array([0.0, -1.0, 0.0])
