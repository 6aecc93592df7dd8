"""Small geometry helpers of the canonical space: pixel grids, back-projection, Umeyama, rotations.

Conventions are the host's (baselines.data.cameras): K in pixels with pixel (row i, col j)
centred at (j + 0.5, i + 0.5); viewmat [4, 4] world -> camera, OpenCV axes.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def grid(height: int, width: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows [h], cols [w]) of the pixels sampled every `stride` pixels (centred in each cell)."""
    start = stride // 2
    return np.arange(start, height, stride), np.arange(start, width, stride)


def rays(K: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """[h, w, 3] camera-frame directions with z = 1 of the grid pixels (K [3, 3])."""
    u = (cols[None, :] + 0.5 - K[0, 2]) / K[0, 0]
    v = (rows[:, None] + 0.5 - K[1, 2]) / K[1, 1]
    u, v = np.broadcast_arrays(u, v)
    return np.stack([u, v, np.ones_like(u)], -1)


def backproject(depth: np.ndarray, K: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """[h, w, 3] camera-frame points from a z-depth map [h, w] sampled on the grid (rows, cols)."""
    return rays(K, rows, cols) * depth[..., None]


def to_world(points: np.ndarray, viewmat: np.ndarray) -> np.ndarray:
    """[..., 3] camera-frame points -> world (R^T (p - t))."""
    return (points - viewmat[:3, 3]) @ viewmat[:3, :3]


def to_camera(points: np.ndarray, viewmat: np.ndarray) -> np.ndarray:
    """[..., 3] world points -> camera frame (R p + t)."""
    return points @ viewmat[:3, :3].T + viewmat[:3, 3]


def relative(view_i: np.ndarray, view_j: np.ndarray) -> np.ndarray:
    """[4, 4] transform taking camera-j coordinates to camera-i coordinates (T_i T_j^-1)."""
    return view_i @ np.linalg.inv(view_j)


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
            with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted similarity (s, R [3, 3], t [3]) minimising sum w |s R src + t - dst|^2.

    src, dst: [P, 3]; weights: [P] >= 0 (uniform when None). Raises ValueError with fewer than
    3 points of positive weight (the fit is undetermined).
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    if (w > 0).sum() < 3 or w.sum() <= 0:
        raise ValueError(f"umeyama: {int((w > 0).sum())} weighted points, at least 3 needed")
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    a, b = src - mu_s, dst - mu_d
    cov = (b * w[:, None]).T @ a
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = float(w @ (a ** 2).sum(1))
    s = float(np.trace(np.diag(S) @ D) / var) if with_scale and var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


def robust_umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
                   rounds: int = 3) -> tuple[float, np.ndarray, np.ndarray]:
    """`umeyama` re-weighted `rounds` times by the Cauchy weight 1 / (1 + (r / 3 median r)^2) of
    each residual r (outliers lose their pull)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    s, R, t = umeyama(src, dst, w)
    for _ in range(rounds - 1):
        r = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
        c = 3.0 * np.median(r[w > 0]) + 1e-12
        s, R, t = umeyama(src, dst, w / (1 + (r / c) ** 2))
    return s, R, t


def rotvec_to_matrix(omega: Tensor) -> Tensor:
    """Rodrigues: [..., 3] axis-angle -> [..., 3, 3] rotation (smooth at 0)."""
    theta2 = (omega ** 2).sum(-1, keepdim=True).unsqueeze(-1)
    theta = torch.sqrt(theta2 + 1e-24)
    zero = torch.zeros_like(omega[..., 0])
    x, y, z = omega.unbind(-1)
    W = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*omega.shape[:-1], 3, 3)
    small = theta2 < 1e-8
    A = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    B = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / (theta2 + 1e-24))
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(W)
    return eye + A * W + B * (W @ W)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle in degrees of a rotation matrix [3, 3]."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
