"""Tiled compositor in vectorised torch: the `cpu` backend's fallback path.

Same rules as `composite_reference` (docs/ARCHITECTURE.md, "baselines/render"), evaluated only
where they can matter: each 16x16 tile composites the depth-sorted list of Gaussians whose
bounding box touches it (`tiles.bin_gaussians`), instead of every pixel against every Gaussian.

Work is organised as [tiles, 256 pixels, S list entries] tensors:

- tiles are sorted by list length (so that padding to the longest list of a batch is small),
  empty tiles are skipped, and tiles are processed in batches whose padded pair count stays under
  a budget (memory is bounded whatever the scene);
- each tile's list is walked in segments of S entries carrying the per-pixel transmittance, and a
  tile leaves the batch once every one of its pixels has stopped (the transmittance rule), so a
  deep stack costs only the entries in front of the stop;
- the backward pass is hand-written (`_TiledComposite`): it recomputes alphas segment by segment
  (walking the lists back to front with a running suffix sum), so no [pixels x Gaussians]
  intermediate is kept between the passes. What is kept: the float64 transmittance at the start
  of each segment, 8 bytes x pixels x (longest list / S).

Every per-pair decision agrees with the reference bit for bit: alpha, the 1/255 skip, the 0.999
clamp, the transmittance and the stop use the same float operations in the same order (the
transmittance is carried in float64 because torch.cumprod on CPU accumulates in float64). So the
two can only differ by the summation order of the final weighted sums (~1e-7 relative in float32).
A compiled implementation must make the same choices to match the reference as closely.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .composite_reference import ALPHA_MAX, TRANSMITTANCE_MIN
from .projection import ALPHA_THRESHOLD, Projection
from .tiles import TILE_SIZE, TileBins, bin_gaussians

DEFAULT_MAX_PAIRS = 1 << 19  # pixel x Gaussian pairs per step: 2 MB float32 temporaries stay cache-friendly
DEFAULT_SEGMENT = 32  # list entries composited per step; also the early-exit granularity
SIGMA_CUTOFF = 30.0  # exp(-30) ~ 1e-13 << 1/255: such pairs are skipped by the alpha threshold


def composite_tiled(
    projection: Projection,
    opacities: Tensor,
    features: Tensor,
    width: int,
    height: int,
    max_pairs: int = DEFAULT_MAX_PAIRS,
    segment: int = DEFAULT_SEGMENT,
) -> tuple[Tensor, Tensor]:
    """Tiled front-to-back compositing of depth-sorted Gaussians (cpu backend, torch path).

    Args:
        projection: projection of N Gaussians (means2d, conics, depths, radii, visible are read).
        opacities: [N] activated opacities. features: [N, C], any C >= 1.
        width, height: image size in pixels.
        max_pairs: upper bound on the pixel x list-entry pairs held in one step (memory bound).
        segment: list entries per step along each tile's list.
    Returns:
        (image [H, W, C] without background, alpha [H, W, 1]); differentiable w.r.t.
        projection.means2d, projection.conics, opacities and features.
    """
    bins = bin_gaussians(projection, width, height, TILE_SIZE)
    return composite_bins(projection.means2d, projection.conics, opacities, features, bins, width, height,
                          max_pairs, segment)


def composite_bins(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    max_pairs: int = DEFAULT_MAX_PAIRS,
    segment: int = DEFAULT_SEGMENT,
) -> tuple[Tensor, Tensor]:
    """`composite_tiled` for tile lists that are already built (e.g. by another binning).

    Args:
        means2d [N, 2], conics [N, 3], opacities [N], features [N, C]; bins: per-tile front-to-back
        Gaussian lists with tile_size 16 covering the image.
    Returns:
        (image [H, W, C], alpha [H, W, 1]).
    """
    if bins.tile_size != TILE_SIZE:
        raise ValueError(f"bins must use tile_size={TILE_SIZE}, got {bins.tile_size}")
    plan = _make_plan(bins, width, height, max_pairs, segment)
    # Under torch.no_grad() the backward never runs: skip what only it needs.
    plan.for_backward = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, opacities, features))
    return _TiledComposite.apply(means2d, conics, opacities, features, plan)


@dataclass
class _Plan:
    """Non-differentiable layout shared by the forward and backward passes."""

    width: int
    height: int
    tiles_x: int
    tiles_y: int
    tile_ids: Tensor  # [T] non-empty tiles, longest list first
    starts: Tensor  # [T] first entry of each tile's list in gaussian_ids
    lengths: Tensor  # [T] list lengths
    gaussian_ids: Tensor  # [M] per-tile depth-sorted Gaussian indices
    tiles_per_batch: int
    segment: int
    for_backward: bool = True  # keep the per-segment transmittance for the backward pass


def _make_plan(bins: TileBins, width: int, height: int, max_pairs: int, segment: int) -> _Plan:
    lengths = bins.offsets[1:] - bins.offsets[:-1]
    tile_ids = torch.nonzero(lengths > 0, as_tuple=False).squeeze(1)
    order = torch.sort(lengths[tile_ids], descending=True, stable=True).indices
    tile_ids = tile_ids[order]
    pixels_per_tile = bins.tile_size * bins.tile_size
    segment = max(1, int(segment))
    tiles_per_batch = max(1, int(max_pairs) // (pixels_per_tile * segment))
    return _Plan(
        width=width, height=height, tiles_x=bins.tiles_x, tiles_y=bins.tiles_y, tile_ids=tile_ids,
        starts=bins.offsets[:-1][tile_ids], lengths=lengths[tile_ids], gaussian_ids=bins.gaussian_ids,
        tiles_per_batch=tiles_per_batch, segment=segment,
    )


def _tile_pixels(tile_ids: Tensor, tiles_x: int, width: int, height: int, dtype: torch.dtype) -> tuple[Tensor, ...]:
    """Pixel centres of whole tiles and which of them lie inside the image.

    Returns:
        px, py: [B, 256] pixel-centre coordinates (same values as the reference's pixel grid);
        inside: [B, 256] bool.
    """
    local = torch.arange(TILE_SIZE * TILE_SIZE, device=tile_ids.device)
    col = (tile_ids % tiles_x)[:, None] * TILE_SIZE + local % TILE_SIZE
    row = (tile_ids // tiles_x)[:, None] * TILE_SIZE + local // TILE_SIZE
    inside = (col < width) & (row < height)
    return col.to(dtype) + 0.5, row.to(dtype) + 0.5, inside


class _Segment:
    """Per-pair quantities of one segment: [B, 256, S] tensors for B tiles and S list entries.

    The expressions mirror composite_reference.composite_pixels operation for operation (in-place
    where that changes nothing), so alphas, transmittances and stop decisions are bitwise those of
    the reference.
    """

    def __init__(self, px, py, ids, valid, means2d, conics, opacities, t_start):
        self.ids = ids
        self.mx, self.my = means2d[ids, 0], means2d[ids, 1]  # [B, S]
        self.a, self.b, self.c = conics[ids, 0], conics[ids, 1], conics[ids, 2]
        self.o = opacities[ids]
        a, b, c = self.a[:, None, :], self.b[:, None, :], self.c[:, None, :]
        dx = px[:, :, None] - self.mx[:, None, :]
        dy = py[:, :, None] - self.my[:, None, :]
        # sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy, same rounding as the reference.
        sigma = a * dx
        sigma.mul_(dx)
        tmp = c * dy
        sigma.add_(tmp.mul_(dy)).mul_(0.5)
        torch.mul(b, dx, out=tmp)
        sigma.add_(tmp.mul_(dy))
        passed = sigma >= 0
        # exp(-sigma) for sigma beyond SIGMA_CUTOFF is far below the alpha threshold whatever the
        # opacity; clamping there changes no decision and avoids slow denormal arithmetic in exp.
        self.gauss = sigma.clamp_(max=SIGMA_CUTOFF).neg_().exp_()
        self.raw = self.o[:, None, :] * self.gauss
        alpha = torch.clamp(self.raw, max=ALPHA_MAX)
        passed &= alpha >= ALPHA_THRESHOLD
        passed &= valid[:, None, :]
        alpha.mul_(passed)
        # Transmittance after each entry, accumulated in float64 from the carried value: the
        # exact products that torch.cumprod forms (in float64) in the reference.
        shape = alpha.shape
        factors = torch.empty((shape[0], shape[1], shape[2] + 1), dtype=torch.float64, device=alpha.device)
        factors[:, :, 0] = t_start
        factors[:, :, 1:] = torch.neg(alpha, out=tmp).add_(1.0)  # 1 - alpha, exactly
        factors.cumprod_(dim=2)
        self.t_end = factors[:, :, -1]  # float64 carry for the next segment
        transmittance = factors.to(alpha.dtype)
        self.keep = transmittance[:, :, 1:] > TRANSMITTANCE_MIN
        self.alpha = alpha.mul_(self.keep)
        self.t_before = transmittance[:, :, :-1]
        self.weights = self.alpha * self.t_before
        self.passed = passed
        self.dx, self.dy = dx, dy


def _segment_ids(plan: _Plan, tiles: Tensor, seg_start: int) -> tuple[Tensor, Tensor]:
    """Gaussian ids [B, S] of list entries seg_start.. of `tiles` (plan positions), and validity.

    Padding entries point at Gaussian 0 (any valid index) and are masked by `valid`.
    """
    pos = seg_start + torch.arange(plan.segment, device=tiles.device)
    valid = pos[None, :] < plan.lengths[tiles][:, None]
    flat = torch.where(valid, plan.starts[tiles][:, None] + pos[None, :], torch.zeros_like(pos)[None, :])
    ids = plan.gaussian_ids[flat]
    return torch.where(valid, ids, torch.zeros_like(ids)), valid


def _batches(plan: _Plan):
    """Plan positions of each batch of tiles (consecutive, so lists of similar length)."""
    n = plan.tile_ids.numel()
    for start in range(0, n, plan.tiles_per_batch):
        yield torch.arange(start, min(n, start + plan.tiles_per_batch), device=plan.tile_ids.device)


def _walk_forward(plan: _Plan, tiles: Tensor, means2d, conics, opacities, features, record: bool):
    """Composite the lists of `tiles` (plan positions) front to back.

    Returns:
        colour [B, 256, C], alpha [B, 256], and when `record` the per-segment
        (active tile rows, float64 transmittance at segment start) for the backward pass.
    """
    dtype = means2d.dtype
    px, py, inside = _tile_pixels(plan.tile_ids[tiles], plan.tiles_x, plan.width, plan.height, dtype)
    n_tiles = tiles.numel()
    colour = features.new_zeros((n_tiles, px.shape[1], features.shape[1]))
    alpha_sum = means2d.new_zeros((n_tiles, px.shape[1]))
    t_carry = torch.ones(px.shape, dtype=torch.float64, device=px.device)
    rows = torch.arange(n_tiles, device=px.device)  # active rows of this batch
    max_len = int(plan.lengths[tiles].max())
    history = []
    for seg_start in range(0, max_len, plan.segment):
        ids, valid = _segment_ids(plan, tiles[rows], seg_start)
        t_start = t_carry[rows]
        seg = _Segment(px[rows], py[rows], ids, valid, means2d, conics, opacities, t_start)
        if record:
            history.append((rows, t_start))
        colour.index_add_(0, rows, torch.bmm(seg.weights, features[ids]))
        alpha_sum.index_add_(0, rows, seg.weights.sum(dim=2))
        t_carry[rows] = seg.t_end
        # A tile leaves once its list is exhausted or every one of its in-image pixels has stopped.
        alive = (plan.lengths[tiles[rows]] > seg_start + plan.segment) & (
            (seg.keep[:, :, -1] & inside[rows]).any(dim=1)
        )
        rows = rows[alive]
        if rows.numel() == 0:
            break
    return colour, alpha_sum, history


def _walk_backward(plan, tiles, history, means2d, conics, opacities, features, g_colour, g_alpha, grads):
    """Accumulate gradients of the lists of `tiles`, walking segments back to front.

    dL/dalpha_i = T_i (g.f_i + g_A) - (sum_{k>i} (g.f_k + g_A) w_k) / (1 - alpha_i), for entries
    that were composited with an unclamped alpha; the suffix sum is carried across segments.
    """
    g_means2d, g_conics, g_opac, g_feat = grads
    dtype = means2d.dtype
    px, py, _ = _tile_pixels(plan.tile_ids[tiles], plan.tiles_x, plan.width, plan.height, dtype)
    suffix = means2d.new_zeros(px.shape)
    for index in range(len(history) - 1, -1, -1):
        rows, t_start = history[index]
        ids, valid = _segment_ids(plan, tiles[rows], index * plan.segment)
        seg = _Segment(px[rows], py[rows], ids, valid, means2d, conics, opacities, t_start)
        feats = features[ids]  # [B, S, C]
        g_col = g_colour[rows]  # [B, 256, C]
        g_feat.index_add_(0, ids.reshape(-1), torch.bmm(seg.weights.transpose(1, 2), g_col).reshape(-1, feats.shape[2]))
        g_total = torch.bmm(g_col, feats.transpose(1, 2)) + g_alpha[rows][:, :, None]  # [B, 256, S]
        contrib = g_total * seg.weights
        csum = torch.cumsum(contrib, dim=2)
        after = (csum[:, :, -1:] - csum) + suffix[rows][:, :, None]  # sum over later entries
        suffix[rows] = suffix[rows] + csum[:, :, -1]
        g_alpha_pair = seg.t_before * g_total
        g_alpha_pair.sub_(after.div_(torch.neg(seg.alpha, out=contrib).add_(1.0)))
        # Gradient reaches o and sigma only through composited, unclamped alphas.
        live = seg.passed & seg.keep
        live &= seg.raw <= ALPHA_MAX
        u = g_alpha_pair.mul_(live).mul_(seg.gauss)  # [B, 256, S] dL/do per pixel
        _accumulate_geometry_grads(seg, u, grads)


def _accumulate_geometry_grads(seg: _Segment, u: Tensor, grads) -> None:
    """Gradients of means2d, conics and opacities from u = dL/do per pair [B, 256, S].

    With dx = px - mx, sigma = 0.5 (a dx^2 + c dy^2) + b dx dy and dL/dsigma = -o u, every
    gradient is a pixel sum of u dx^k dy^l (k + l <= 2) times per-Gaussian factors.
    """
    g_means2d, g_conics, g_opac, _ = grads
    dx, dy = seg.dx, seg.dy
    udx, udy = u * dx, u * dy
    m0 = u.sum(dim=1)
    s_dx, s_dy = udx.sum(dim=1), udy.sum(dim=1)
    s_dxdx, s_dxdy, s_dydy = (udx.mul_(dx)).sum(dim=1), (udy * dx).sum(dim=1), (udy.mul_(dy)).sum(dim=1)
    o = seg.o
    g_m = torch.stack([o * (seg.a * s_dx + seg.b * s_dy), o * (seg.b * s_dx + seg.c * s_dy)], dim=-1)
    g_c = torch.stack([-0.5 * o * s_dxdx, -o * s_dxdy, -0.5 * o * s_dydy], dim=-1)
    flat_ids = seg.ids.reshape(-1)
    g_opac.index_add_(0, flat_ids, m0.reshape(-1))
    g_means2d.index_add_(0, flat_ids, g_m.reshape(-1, 2))
    g_conics.index_add_(0, flat_ids, g_c.reshape(-1, 3))


def _tiles_to_image(per_tile: Tensor, plan: _Plan) -> Tensor:
    """[T_all, 256, C] tile-major values -> [H, W, C] image (crops the partial border tiles)."""
    c = per_tile.shape[-1]
    img = per_tile.reshape(plan.tiles_y, plan.tiles_x, TILE_SIZE, TILE_SIZE, c).permute(0, 2, 1, 3, 4)
    return img.reshape(plan.tiles_y * TILE_SIZE, plan.tiles_x * TILE_SIZE, c)[: plan.height, : plan.width]


def _image_to_tiles(image: Tensor, plan: _Plan) -> Tensor:
    """[H, W, C] image -> [T_all, 256, C] tile-major values (zero outside the image)."""
    c = image.shape[-1]
    padded = image.new_zeros((plan.tiles_y * TILE_SIZE, plan.tiles_x * TILE_SIZE, c))
    padded[: plan.height, : plan.width] = image
    tiles = padded.reshape(plan.tiles_y, TILE_SIZE, plan.tiles_x, TILE_SIZE, c).permute(0, 2, 1, 3, 4)
    return tiles.reshape(plan.tiles_y * plan.tiles_x, TILE_SIZE * TILE_SIZE, c)


class _TiledComposite(torch.autograd.Function):
    """Forward: tiled compositing. Backward: hand-written, recomputing alphas per segment."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, plan: _Plan):
        n_all = plan.tiles_x * plan.tiles_y
        pixels = TILE_SIZE * TILE_SIZE
        colour = features.new_zeros((n_all, pixels, features.shape[1]))
        alpha = means2d.new_zeros((n_all, pixels, 1))
        record = plan.for_backward
        histories = []
        with torch.no_grad():
            for tiles in _batches(plan):
                col, alp, hist = _walk_forward(plan, tiles, means2d, conics, opacities, features, record)
                colour[plan.tile_ids[tiles]] = col
                alpha[plan.tile_ids[tiles], :, 0] = alp
                histories.append(hist)
        ctx.plan = plan
        ctx.histories = histories
        ctx.save_for_backward(means2d, conics, opacities, features)
        return _tiles_to_image(colour, plan), _tiles_to_image(alpha, plan)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_image, g_alpha):
        means2d, conics, opacities, features = ctx.saved_tensors
        plan = ctx.plan
        n = means2d.shape[0]
        grads = (
            means2d.new_zeros((n, 2)), conics.new_zeros((n, 3)), opacities.new_zeros((n,)),
            features.new_zeros((n, features.shape[1])),
        )
        with torch.no_grad():
            g_colour_tiles = _image_to_tiles(g_image, plan)
            g_alpha_tiles = _image_to_tiles(g_alpha, plan)[:, :, 0]
            for tiles, hist in zip(_batches(plan), ctx.histories):
                if not hist:
                    continue
                g_col = g_colour_tiles[plan.tile_ids[tiles]]
                g_alp = g_alpha_tiles[plan.tile_ids[tiles]]
                _walk_backward(plan, tiles, hist, means2d, conics, opacities, features, g_col, g_alp, grads)
        g_means2d, g_conics, g_opac, g_feat = grads
        return g_means2d, g_conics, g_opac, g_feat, None

