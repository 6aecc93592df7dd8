"""Full flow and camera flow of a Gaussian model between two views (DESIGN.md section 5).

Full flow, rendered in ONE rasterization pass as extra feature channels of view a:

    each Gaussian i maps a pixel q of view a to   A_i (q - m_a,i) + m_b,i,
        A_i = sqrt(S_b,i) sqrt(S_a,i)^-1          (symmetric 2x2 square roots; GaussianFlow's map)
    blended:  F_a->b(q) = (M(q) q + c(q)) / alpha(q) - q,
        M(q) = sum_i w_i(q) A_i  (4 channels),   c(q) = sum_i w_i(q) (m_b,i - A_i m_a,i)  (2 channels)

m and S are the projected means and 2D covariances (eps2d blur included: those are the
Gaussians the pixels were blended with). sqrt(S_a)^-1 = sqrt(S_a^-1) is built from the conic
that the projection already computes. A 7th channel v_i = 1 for Gaussians that are in front of
camera b (0 otherwise, with A_i = I and c_i = 0 so their values stay finite): a pixel is valid
when alpha(q) >= min_alpha and sum w v / alpha >= 0.99. Invalid pixels get flow 0 and are masked;
no NaN or inf reaches values or gradients.

Camera flow, from view a's expected depth D_a and the two cameras (paper appendix A.3):

    F^cam_a->b(q) = proj(K_b T_b T_a^-1 (D_a(q) K_a^-1 [q, 1])) - q

Pixels: (x, y) = (column + 0.5, row + 0.5). `full_flow_dense` is the obviously-correct twin used
as the test oracle: per-pixel, per-Gaussian blending weights from the reference rasterizer.
"""
from __future__ import annotations

import functools

import torch
from torch import Tensor

from baselines.render import Projection

NEAR = 0.01  # the rasterizer's near plane
MAX_FOOTPRINT_PX = 1e4  # screen std (px) beyond which a projected Gaussian is no flow target: wider than any image
MAX_SCREEN_PX = 1e6  # |projected centre| (px) beyond which likewise
VALID_COVERAGE = 0.99  # share of a pixel's weight that must come from Gaussians valid in view b
FLOW_CHANNELS = 7  # A (4) + c (2) + validity (1)


def pixel_grid(height: int, width: int, like: Tensor) -> Tensor:
    """[H, W, 2] pixel-centre coordinates (x, y) on `like`'s device and dtype (cached: read-only)."""
    return _pixel_grid(int(height), int(width), like.device, like.dtype)


@functools.lru_cache(maxsize=16)
def _pixel_grid(height: int, width: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    # built once per size: a training step asks for it in every flow map and warp. Never as an
    # inference tensor (a first call under torch.inference_mode would cache one, and autograd cannot
    # save it for backward later)
    with torch.inference_mode(False):
        ys = torch.arange(height, device=device, dtype=dtype) + 0.5
        xs = torch.arange(width, device=device, dtype=dtype) + 0.5
        grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
        return torch.stack((grid_x, grid_y), dim=-1)


def sqrtm_spd2(a: Tensor, b: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Symmetric square root of [[a, b], [b, c]] (SPD), elementwise: returns its (a, b, c).

    sqrt(M) = sqrt(k) (M' + s I) / t with M' = M / k, k = tr M, s = sqrt(det M'), t = sqrt(tr M' + 2 s).
    Scaling by the trace first keeps det from overflowing float32: a Gaussian whose deformed scale
    blew up has a screen covariance of ~1e21 px^2 in another view, whose raw det (~1e40) is inf and
    made NaN flow channels (a real NVIDIA capture, fine iteration ~420). det' is clamped at a tiny
    positive value so near-singular inputs give finite values and gradients.
    """
    k = (a + c).clamp_min(1e-20)
    a1, b1, c1 = a / k, b / k, c / k
    s = (a1 * c1 - b1 * b1).clamp_min(1e-20).sqrt()
    scale = k.sqrt() / (a1 + c1 + 2.0 * s).clamp_min(1e-20).sqrt()
    return (a1 + s) * scale, b1 * scale, (c1 + s) * scale


def valid_in_view(projection: Projection, near: float = NEAR) -> Tensor:
    """[N] bool: in front of the camera's near plane with finite screen values (flow target exists)."""
    finite = torch.isfinite(projection.means2d).all(dim=1) & torch.isfinite(projection.cov2d).flatten(1).all(dim=1)
    return (projection.depths >= near) & finite


def plausible_on_screen(projection: Projection) -> Tensor:
    """[N] bool: a screen footprint (sqrt of the covariance's trace) below MAX_FOOTPRINT_PX and a
    centre within MAX_SCREEN_PX. A dynamic Gaussian whose deformed scale blew up at t_b (a real
    NVIDIA capture: cov ~1e21 px^2, 1e10 px flows) gives no usable target, and its numbers made
    the flow loss's gradients overflow. NaN compares False."""
    trace = projection.cov2d[:, 0, 0] + projection.cov2d[:, 1, 1]
    return (trace <= MAX_FOOTPRINT_PX ** 2) & (projection.means2d.abs() <= MAX_SCREEN_PX).all(dim=1)


def flow_features(proj_a: Projection, proj_b: Projection, near: float = NEAR) -> Tensor:
    """Per-Gaussian channels [N, 7] = (A_00, A_01, A_10, A_11, c_x, c_y, v) for view a's pass.

    v = 1 where the Gaussian has a flow target: valid in both views (`valid_in_view`), a finite
    conic in a, and a plausible footprint in both (`plausible_on_screen`); elsewhere A = I, c = 0.
    The compiled CPU kernel (flow_kernel.py) where it can run, else `flow_features_torch`.

    Args:
        proj_a, proj_b: the same N Gaussians projected into view a (at t_a) and view b (at t_b).
    """
    from . import flow_kernel  # a compiled library behind ctypes: loaded on first use

    reason = flow_kernel.unusable_reason(proj_a, proj_b)
    if reason is None:
        return flow_kernel.flow_features_kernel(proj_a, proj_b, near, MAX_FOOTPRINT_PX ** 2, MAX_SCREEN_PX)
    flow_kernel.log_fallback_once(reason)
    return flow_features_torch(proj_a, proj_b, near)


def flow_features_torch(proj_a: Projection, proj_b: Projection, near: float = NEAR) -> Tensor:
    """`flow_features` in torch: the oracle of the compiled kernel's tests and its fallback."""
    valid = (valid_in_view(proj_b, near) & valid_in_view(proj_a, near) & plausible_on_screen(proj_a)
             & plausible_on_screen(proj_b) & torch.isfinite(proj_a.conics).all(dim=1))
    # Invalid rows get harmless inputs BEFORE the math, so their extreme numbers reach neither the
    # channels nor (through torch.where's zero branch times inf) the gradients.
    cov_b = torch.where(valid[:, None, None], proj_b.cov2d, torch.eye(2, dtype=proj_b.cov2d.dtype,
                                                                      device=proj_b.cov2d.device))
    conic_a = torch.where(valid[:, None], proj_a.conics, proj_a.conics.new_tensor([1.0, 0.0, 1.0]))
    # sqrt(S_b) and sqrt(S_a)^-1 = sqrt(S_a^-1) (the conic is (a, b, c) of S_a^-1), in one call on [2, N]
    # (a step is bound by the number of small kernels on a GPU, not by their size)
    r_a, r_b, r_c = sqrtm_spd2(torch.stack((cov_b[:, 0, 0], conic_a[:, 0])), torch.stack((cov_b[:, 0, 1], conic_a[:, 1])),
                               torch.stack((cov_b[:, 1, 1], conic_a[:, 2])))
    # A = sqrt(S_b) sqrt(S_a)^-1 and c = m_b - A m_a written out per entry (a batched 2x2 matmul is
    # slower on a CPU); invalid rows' means are zeroed before they enter
    (sb_a, ia_a), (sb_b, ia_b), (sb_c, ia_c) = r_a.unbind(0), r_b.unbind(0), r_c.unbind(0)
    zero = torch.zeros((), dtype=proj_a.means2d.dtype, device=proj_a.means2d.device)
    ma = torch.where(valid[:, None], proj_a.means2d, zero)
    mb = torch.where(valid[:, None], proj_b.means2d, zero)
    a00, a01 = sb_a * ia_a + sb_b * ia_b, sb_a * ia_b + sb_b * ia_c
    a10, a11 = sb_b * ia_a + sb_c * ia_b, sb_b * ia_b + sb_c * ia_c
    A = torch.stack((a00, a01, a10, a11), dim=1)  # [N, 4]
    c = mb - torch.stack((a00 * ma[:, 0] + a01 * ma[:, 1], a10 * ma[:, 0] + a11 * ma[:, 1]), dim=1)
    identity = A.new_tensor([1.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    channels = torch.where(valid[:, None], torch.cat((A, c), dim=1), identity)
    return torch.cat((channels, valid.to(channels.dtype).unsqueeze(1)), dim=1)


def full_flow(maps: Tensor, alpha: Tensor, min_alpha: float = 0.5) -> tuple[Tensor, Tensor]:
    """Blended full flow of view a from its composited flow channels.

    Args:
        maps: [H, W, 7] composited `flow_features` (no background term).
        alpha: [H, W, 1] view a's accumulated opacity.
    Returns:
        (flow [H, W, 2] in pixels, 0 where invalid; valid [H, W] bool).
    """
    h, w = maps.shape[:2]
    q = pixel_grid(h, w, maps)
    covered = alpha[..., 0] >= max(min_alpha, 1e-6)
    alpha_safe = torch.where(covered, alpha[..., 0], torch.ones_like(alpha[..., 0]))
    mx = maps[..., 0] * q[..., 0] + maps[..., 1] * q[..., 1] + maps[..., 4]
    my = maps[..., 2] * q[..., 0] + maps[..., 3] * q[..., 1] + maps[..., 5]
    flow = torch.stack((mx / alpha_safe, my / alpha_safe), dim=-1) - q
    valid = covered & (maps[..., 6] / alpha_safe >= VALID_COVERAGE) & torch.isfinite(flow).all(dim=-1)
    return torch.where(valid.unsqueeze(-1), flow, torch.zeros_like(flow)), valid


def relative_pose(viewmat_a: Tensor, viewmat_b: Tensor) -> tuple[Tensor, Tensor]:
    """(R [3,3], t [3]) mapping camera-a coordinates to camera-b coordinates."""
    rotation = viewmat_b[:3, :3] @ viewmat_a[:3, :3].T
    return rotation, viewmat_b[:3, 3] - rotation @ viewmat_a[:3, 3]


def camera_flow(depth: Tensor, alpha: Tensor, K_a: Tensor, viewmat_a: Tensor, K_b: Tensor, viewmat_b: Tensor,
                min_alpha: float = 0.5, near: float = NEAR) -> tuple[Tensor, Tensor]:
    """Flow of view a's pixels if the scene were static: back-project with D_a, project into b.

    Args:
        depth, alpha: [H, W, 1] view a's expected depth and opacity.
        K_a, K_b: [3, 3]; viewmat_a, viewmat_b: [4, 4] world->camera.
    Returns:
        (flow [H, W, 2], valid [H, W] bool): invalid where alpha < min_alpha, the depth is not a
        finite value >= near, or the point lands behind camera b's near plane.
    """
    h, w = depth.shape[:2]
    q = pixel_grid(h, w, depth)
    d = depth[..., 0]
    valid = (alpha[..., 0] >= max(min_alpha, 1e-6)) & torch.isfinite(d) & (d >= near)
    d = torch.where(valid, d, torch.ones_like(d))
    K_a, K_b = K_a.to(depth.dtype), K_b.to(depth.dtype)
    x = (q[..., 0] - K_a[0, 2]) / K_a[0, 0]
    y = (q[..., 1] - K_a[1, 2]) / K_a[1, 1]
    points_a = torch.stack((x * d, y * d, d), dim=-1)
    rotation, translation = relative_pose(viewmat_a.to(depth.dtype), viewmat_b.to(depth.dtype))
    points_b = points_a @ rotation.T + translation
    z = points_b[..., 2]
    valid = valid & (z >= near)
    z = torch.where(valid, z, torch.ones_like(z))
    px = K_b[0, 0] * points_b[..., 0] / z + K_b[0, 2]
    py = K_b[1, 1] * points_b[..., 1] / z + K_b[1, 2]
    flow = torch.stack((px, py), dim=-1) - q
    valid = valid & torch.isfinite(flow).all(dim=-1)
    return torch.where(valid.unsqueeze(-1), flow, torch.zeros_like(flow)), valid


def camera_motion_pixels(K_b: Tensor, viewmat_a: Tensor, viewmat_b: Tensor, depth: float) -> float:
    """Rough image motion (pixels) a static point at `depth` sees between the two cameras."""
    rotation, translation = relative_pose(viewmat_a.double(), viewmat_b.double())
    cos = ((torch.trace(rotation) - 1.0) / 2.0).clamp(-1.0, 1.0)
    angle = float(torch.arccos(cos))
    focal = float(K_b[:2, :2].diagonal().double().mean())
    return focal * (angle + float(translation.norm()) / max(depth, 1e-6))


def full_flow_dense(weights: Tensor, proj_a: Projection, proj_b: Projection) -> Tensor:
    """Test oracle: the blended flow from explicit per-pixel, per-Gaussian weights.

    Args:
        weights: [H, W, N] blending weights w_i(q) of view a (e.g. the reference rasterizer
            compositing an identity feature matrix).
    Returns:
        [H, W, 2] = sum_i w_i (A_i (q - m_a,i) + m_b,i) / sum_i w_i - q, with A_i built from explicit
        matrix square roots (eigendecomposition), independent of `flow_features`.
    """
    h, w, n = weights.shape
    q = pixel_grid(h, w, weights)

    def sqrtm(m: Tensor) -> Tensor:
        values, vectors = torch.linalg.eigh(m)
        return vectors @ torch.diag_embed(values.clamp_min(0).sqrt()) @ vectors.transpose(-1, -2)

    A = sqrtm(proj_b.cov2d) @ torch.linalg.inv(sqrtm(proj_a.cov2d))  # [N, 2, 2]
    offsets = q.unsqueeze(2) - proj_a.means2d  # [H, W, N, 2]
    targets = torch.einsum("nij,hwnj->hwni", A, offsets) + proj_b.means2d
    alpha = weights.sum(-1, keepdim=True).clamp_min(1e-12)
    return (weights.unsqueeze(-1) * targets).sum(2) / alpha - q
