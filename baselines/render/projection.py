"""Projection stage: 3D Gaussians -> screen-space means, covariances, conics, depths and radii.

This is the torch implementation shared by the `reference` and `cpu` backends (gsplat fuses its
own CUDA version with the same rules). It follows gsplat's EWA projection:

    p = R mu + t                                      camera-space mean
    Sigma_cam = R (Rq S S Rq^T) R^T                   3D covariance in camera axes
    (computed as T T^T with T = J R Rq S, elementwise; see the comment in the function)
    J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]] with tx/z, ty/z clamped to 1.3x the half FOV
    Sigma_2d = J Sigma_cam J^T + eps2d I              (the "blur" keeps tiny Gaussians >= ~1 px)

Every quantity stays finite for Gaussians behind the camera, straddling the near plane or with
extreme scales: such Gaussians are marked invisible and their values are computed from safe
stand-ins (torch.where on the *inputs*, not only the outputs, so no NaN leaks into gradients).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

# gsplat's rules, shared by all backends (DESIGN.md section 3).
ALPHA_THRESHOLD = 1.0 / 255.0
EXTEND_MAX = 3.33  # sqrt(2 ln 255): beyond this Mahalanobis radius alpha < 1/255 even at opacity 1
FOV_CLAMP_MARGIN = 0.3  # Jacobian clamp at (1 + margin) x the half field of view
RADIUS_CAP = float(2**24)  # keeps int32 radii exact and finite for absurd covariances


@dataclass
class Projection:
    """Screen-space description of N Gaussians for one camera.

    Attributes:
        means2d: [N, 2] pixel coordinates (x = column, y = row; pixel (i, j) centre at (j+.5, i+.5)).
        cov2d:   [N, 2, 2] screen-space covariance including the eps2d blur.
        conics:  [N, 3] (a, b, c) of the inverse covariance [[a, b], [b, c]].
        depths:  [N] camera-space z of the means.
        radii:   [N, 2] int32 half-extents (x, y) in pixels of the bounding box holding every
                 pixel with alpha >= 1/255; 0 where not visible.
        visible: [N] bool: in front of the near plane, finite, non-degenerate, box overlaps image.

    Invisible Gaussians inside the depth range (off the image, or fainter than 1/255) keep their
    true means2d, cov2d and conics (flow rendering reads them: where view a's pixels go in view b);
    outside the depth range they are finite stand-ins (means2d at the principal point, an identity
    conic). Every backend follows this (the gsplat backend fills its culled entries accordingly).
    """

    means2d: Tensor
    cov2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    visible: Tensor

    def __getitem__(self, key: str) -> Tensor:  # dict-style access, as gsplat's meta
        return getattr(self, key)

    def keys(self) -> list[str]:
        return [f.name for f in fields(self)]


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions.

    Args:
        quats: [N, 4] (w, x, y, z), any norm (normalised here; a zero quaternion gives identity).
    Returns:
        [N, 3, 3]
    """
    norm = quats.norm(dim=-1, keepdim=True)
    safe = torch.where(norm > 1e-12, quats, torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device))
    w, x, y, z = (safe / safe.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariances R S S R^T.

    Args:
        quats: [N, 4] wxyz. scales: [N, 3] activated (positive) standard deviations.
    Returns:
        [N, 3, 3]
    """
    rs = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # R @ diag(s)
    return rs @ rs.transpose(-1, -2)


def project_gaussians_torch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    opacities: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """EWA projection of N Gaussians into one pinhole camera (differentiable torch).

    Args:
        means: [N, 3] world positions. quats: [N, 4] wxyz. scales: [N, 3] activated scales.
        viewmat: [4, 4] world-to-camera (OpenCV axes). K: [3, 3] pixel intrinsics.
        width, height: image size in pixels.
        opacities: [N] activated opacities; when given, the bounding box shrinks to where
            alpha can reach 1/255 and Gaussians with opacity < 1/255 are invisible (gsplat).
        near, far: depth range; eps2d: screen-space blur added to the covariance diagonal.
    Returns:
        Projection with [N]-leading tensors (see its docstring).
    """
    dtype = means.dtype
    R = viewmat[:3, :3]
    t = viewmat[:3, 3]
    p_cam = means @ R.T + t  # [N, 3]
    x, y, z = p_cam.unbind(-1)

    in_depth_range = (z >= near) & (z <= far)  # gsplat culls z < near or z > far
    # Safe stand-ins for invisible Gaussians so that no inf/NaN reaches any gradient.
    z_safe = torch.where(in_depth_range, z, torch.ones_like(z))
    x_safe = torch.where(in_depth_range, x, torch.zeros_like(x))
    y_safe = torch.where(in_depth_range, y, torch.zeros_like(y))

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + FOV_CLAMP_MARGIN * tan_fovx
    lim_x_neg = cx / fx + FOV_CLAMP_MARGIN * tan_fovx
    lim_y_pos = (height - cy) / fy + FOV_CLAMP_MARGIN * tan_fovy
    lim_y_neg = cy / fy + FOV_CLAMP_MARGIN * tan_fovy
    tx = z_safe * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x_safe / z_safe))
    ty = z_safe * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y_safe / z_safe))

    # cov2d = J R Rq S S Rq^T R^T J^T = T T^T with T = J R Rq S ([N, 2, 3]). J's two rows are
    # combinations of R's rows, so T's rows are built elementwise: no batched 3x3 matmuls, whose
    # per-call overhead dominated the projection (forward and backward) on CPU.
    j_x, j_xz = fx / z_safe, -fx * tx / z_safe**2  # J row 0 = (j_x, 0, j_xz)
    j_y, j_yz = fy / z_safe, -fy * ty / z_safe**2  # J row 1 = (0, j_y, j_yz)
    row0 = j_x.unsqueeze(1) * R[0] + j_xz.unsqueeze(1) * R[2]  # [N, 3] = (J R)[0]
    row1 = j_y.unsqueeze(1) * R[1] + j_yz.unsqueeze(1) * R[2]
    rot_scaled = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # Rq diag(s), [N, 3, 3]
    t0 = (row0.unsqueeze(2) * rot_scaled).sum(dim=1)  # [N, 3] = (J R Rq S)[0]
    t1 = (row1.unsqueeze(2) * rot_scaled).sum(dim=1)
    a0, c0 = (t0 * t0).sum(dim=1), (t1 * t1).sum(dim=1)
    a, b, c = a0 + eps2d, (t0 * t1).sum(dim=1), c0 + eps2d
    cov2d = torch.stack([a, b, b, c], dim=-1).reshape(-1, 2, 2)
    # det(T T^T + eps I) without the cancellation of a*c - b^2 (needle-like Gaussians have
    # a*c ~ b^2): |t0|^2 |t1|^2 - (t0.t1)^2 = |t0 x t1|^2 (Lagrange's identity).
    det = (torch.linalg.cross(t0, t1) ** 2).sum(dim=1) + eps2d * (a0 + c0) + eps2d * eps2d

    finite = torch.isfinite(cov2d).flatten(1).all(dim=1) & torch.isfinite(p_cam).all(dim=1)
    ok = in_depth_range & finite & (det > 0)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    a_s = torch.where(ok, a, torch.ones_like(a))
    b_s = torch.where(ok, b, torch.zeros_like(b))
    c_s = torch.where(ok, c, torch.ones_like(c))
    conics = torch.stack([c_s / det_safe, -b_s / det_safe, a_s / det_safe], dim=-1)
    cov2d = torch.stack([a_s, b_s, b_s, c_s], dim=-1).reshape(-1, 2, 2)

    means2d = torch.stack([fx * x_safe / z_safe + cx, fy * y_safe / z_safe + cy], dim=-1)

    with torch.no_grad():
        extend = torch.full_like(z, EXTEND_MAX)
        if opacities is not None:
            o = opacities.detach().to(dtype)
            ok = ok & (o >= ALPHA_THRESHOLD)
            extend = torch.minimum(extend, torch.sqrt(2.0 * torch.log(torch.clamp(o / ALPHA_THRESHOLD, min=1.0))))
        rx = torch.ceil(extend * torch.sqrt(torch.clamp(a_s, min=0.0))).clamp(max=RADIUS_CAP)
        ry = torch.ceil(extend * torch.sqrt(torch.clamp(c_s, min=0.0))).clamp(max=RADIUS_CAP)
        mx, my = means2d[:, 0].detach(), means2d[:, 1].detach()
        on_screen = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        visible = ok & on_screen & ((rx > 0) | (ry > 0)) & torch.isfinite(means2d.detach()).all(dim=1)
        radii = torch.stack([rx, ry], dim=-1).to(torch.int32) * visible.unsqueeze(-1)

    return Projection(means2d=means2d, cov2d=cov2d, conics=conics, depths=z, radii=radii, visible=visible)


def max_extend_for_opacity(opacity: float) -> float:
    """Mahalanobis radius beyond which alpha = opacity * exp(-r^2/2) < 1/255 (capped at 3.33)."""
    if opacity < ALPHA_THRESHOLD:
        return 0.0
    return min(EXTEND_MAX, math.sqrt(2.0 * math.log(opacity / ALPHA_THRESHOLD)))
