"""Tile binning shared by the tiled backends (torch tiled path and the compiled CPU kernel).

Each visible Gaussian is listed in every tile its bounding box touches; the (tile, Gaussian)
intersections are sorted by tile, then front to back. Depth ties keep the Gaussian index order,
the same order as the dense reference, so backends agree even on coincident depths.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .projection import Projection

TILE_SIZE = 16


@dataclass
class TileBins:
    """Per-tile, depth-sorted Gaussian lists.

    Attributes:
        tile_size: tile edge in pixels.
        tiles_x, tiles_y: grid size (ceil(width / tile_size), ceil(height / tile_size)).
        offsets: [tiles_x * tiles_y + 1] int64; tile k's Gaussians are
            gaussian_ids[offsets[k]:offsets[k + 1]], tiles in row-major order.
        gaussian_ids: [M] int64 Gaussian indices, front to back within each tile.
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    offsets: Tensor
    gaussian_ids: Tensor

    @property
    def num_intersections(self) -> int:
        return int(self.gaussian_ids.numel())


def tile_ranges(projection: Projection, width: int, height: int, tile_size: int) -> tuple[Tensor, ...]:
    """Tile rectangles [x0, x1) x [y0, y1) covered by each Gaussian's box (empty if invisible).

    Returns:
        x0, x1, y0, y1: [N] int64 each.
    """
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    m = projection.means2d.detach().to(torch.float64)
    r = projection.radii.to(torch.float64)
    x0 = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tiles_x)
    x1 = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tiles_x)
    y0 = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, tiles_y)
    y1 = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, tiles_y)
    vis = projection.visible
    x0, x1, y0, y1 = (v.to(torch.int64) for v in (x0, x1, y0, y1))
    x1 = torch.where(vis, x1, x0)
    y1 = torch.where(vis, y1, y0)
    return x0, x1, y0, y1


def bin_gaussians(projection: Projection, width: int, height: int, tile_size: int = TILE_SIZE) -> TileBins:
    """Build depth-sorted per-tile Gaussian lists (no gradients involved).

    Args:
        projection: projection of N Gaussians (means2d, radii, depths, visible are read).
        width, height: image size in pixels.
    Returns:
        TileBins.
    """
    device = projection.depths.device
    n = projection.depths.shape[0]
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    with torch.no_grad():
        x0, x1, y0, y1 = tile_ranges(projection, width, height, tile_size)
        span_x = (x1 - x0).clamp(min=0)
        counts = span_x * (y1 - y0).clamp(min=0)
        total = int(counts.sum().item())
        if total == 0:
            return TileBins(tile_size, tiles_x, tiles_y, torch.zeros(n_tiles + 1, dtype=torch.int64, device=device),
                            torch.zeros(0, dtype=torch.int64, device=device))
        gauss = torch.repeat_interleave(torch.arange(n, device=device), counts)
        first = torch.cumsum(counts, 0) - counts  # start of each Gaussian's run
        local = torch.arange(total, device=device) - first[gauss]
        sx = span_x[gauss]
        tile = (y0[gauss] + local // sx) * tiles_x + (x0[gauss] + local % sx)
        # Rank of each Gaussian in a stable front-to-back order: ties resolved by index.
        depth_rank = torch.empty(n, dtype=torch.int64, device=device)
        depth_rank[torch.sort(projection.depths.detach(), stable=True).indices] = torch.arange(n, device=device)
        key = tile * n + depth_rank[gauss]
        order = torch.sort(key).indices
        gaussian_ids = gauss[order]
        per_tile = torch.bincount(tile, minlength=n_tiles)
        offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=device)
        offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(tile_size, tiles_x, tiles_y, offsets, gaussian_ids)
