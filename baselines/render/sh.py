"""Real spherical harmonics colour, with the constants and sign conventions of 3DGS/4DGS.

Coefficients are stored as 4DGS stores them (`GaussianModel.get_features`): [N, K, 3] with
K >= (degree + 1)^2 coefficients per colour channel, coefficient 0 being the DC term. The basis
is the real SH basis up to degree 3 with 3DGS's signs (e.g. the degree-1 terms are
-C1 y, +C1 z, -C1 x); `sh_to_rgb` is the colour 3DGS's renderer assigns to a Gaussian seen from
a camera: clamp_min(SH(view direction) + 0.5, 0).
"""
from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_coefficients(degree: int) -> int:
    """(degree + 1)^2 coefficients per channel."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis functions (3DGS signs) at unit directions.

    Args:
        degree: 0..3. dirs: [..., 3] unit vectors (x, y, z).
    Returns:
        [..., (degree + 1)^2]
    """
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        basis += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(basis, dim=-1)


def _check(degree: int, sh: Tensor, dirs: Tensor) -> None:
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"degree must be an integer in [0, {MAX_SH_DEGREE}], got {degree!r}")
    if sh.dim() != 3 or sh.shape[1] < num_sh_coefficients(degree):
        raise ValueError(
            f"sh must have shape [N, K, C] with K >= {num_sh_coefficients(degree)} for degree {degree}, "
            f"got {tuple(sh.shape)}"
        )
    if dirs.shape != (sh.shape[0], 3):
        raise ValueError(f"dirs must have shape [N, 3] with N={sh.shape[0]}, got {tuple(dirs.shape)}")


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH colour at unit directions (no +0.5 offset, no clamp).

    Args:
        degree: active SH degree 0..3 (only the first (degree + 1)^2 coefficients are read).
        sh: [N, K, C] coefficients (C = 3 for RGB). dirs: [N, 3] unit view directions.
    Returns:
        [N, C]
    """
    _check(degree, sh, dirs)
    basis = sh_basis(degree, dirs.to(sh.dtype))  # [N, K']
    return torch.einsum("nk,nkc->nc", basis, sh[:, : basis.shape[1]])


def sh_to_rgb(sh: Tensor, means: Tensor, camera_center: Tensor, degree: int) -> Tensor:
    """Per-Gaussian view-dependent colour, as 3DGS's renderer computes it.

    Args:
        sh: [N, K, 3] coefficients. means: [N, 3] world positions. camera_center: [3] world
        position of the camera. degree: active SH degree.
    Returns:
        [N, 3] colours = clamp_min(eval_sh(degree, sh, normalize(means - camera_center)) + 0.5, 0).
        A Gaussian exactly at the camera centre gets a zero direction (only the DC term counts).
    """
    if camera_center.shape != (3,):
        raise ValueError(f"camera_center must have shape [3], got {tuple(camera_center.shape)}")
    dirs = torch.nn.functional.normalize(means - camera_center, dim=-1)
    return torch.clamp_min(eval_sh(degree, sh, dirs) + 0.5, 0.0)


def RGB2SH(rgb: Tensor) -> Tensor:
    """DC coefficient whose colour (SH_C0 * dc + 0.5) is `rgb`."""
    return (rgb - 0.5) / SH_C0


def SH2RGB(sh: Tensor) -> Tensor:
    """Colour of a DC coefficient: SH_C0 * sh + 0.5."""
    return sh * SH_C0 + 0.5
