"""Bilinear lookups on many 2D feature planes, multiplied in groups (HexPlane's inner loop).

Semantics: for every plane p (shape [1, C, H, W], sampled at (u, v) = (coord[u_axis], coord[v_axis])
in [-1, 1]) the sample equals ``F.grid_sample(plane, ..., mode='bilinear', padding_mode='border',
align_corners=True)``, gradients included (a clamped coordinate gets none). Consecutive groups of
``group`` planes are multiplied elementwise; the groups' products are concatenated.

Why not ``grid_sample``: on CPU its backward is a per-channel scatter, single-threaded for one
batch item, and it dominates a 4DGS training step. Here the planes form one channels-last table
[sum(H*W), C]; a sample is a 4-row weighted ``embedding_bag`` (a fused, vectorised kernel). The
table gradient orders each plane's points by cell once and sums their sample gradients per cell
with ``embedding_bag`` again; the coordinate gradient uses ``embedding_bag`` with the derivative
weights. The work runs plane by plane on [N, C] tensors: one [P, N, C] tensor
would exceed the allocator's reuse threshold at 100k points and page-fault on every call.

Two engines: where it can (CPU, float32/float64, a C++ compiler), the lookup runs the compiled
kernel of plane_kernel.py (one pass over the points instead of ~25 small ops per plane; about 3x
faster at 10k points); the torch path below is the fallback and the kernel's test oracle. The
choice is made per call; both give the same values and gradients to float rounding.

Two entry points: ``plane_product_lookup(table, ...)`` takes a table built by
``planes_to_table`` (a differentiable copy of the planes); ``shared_plane_product_lookup(planes,
table, ...)`` takes planes that ARE views of one table (``pack_planes``, ``shared_table``), so a
call copies nothing and the planes' gradients come back as views of one gradient table. The
HexPlane field uses the second; the first is the general form and the second's test oracle.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from baselines.fourdgs import plane_kernel

# A plane with more cells than this many per point gets its table gradient by index_add_ (see
# _add_table_grad); denser planes by sorted per-cell bags.
INDEX_ADD_CELLS_PER_POINT = 4


@dataclass(frozen=True)
class PlaneLayout:
    """Where each plane sits in the concatenated table and which coordinates address it.

    Per plane p: ``u_axis``/``v_axis`` index the coordinates (spatial columns first, then time
    columns), ``width``/``height`` are W/H, ``offset`` its first table row, ``shifts`` the row
    offsets of its 4 bilinear corners from the top-left one (0 for a corner outside a 1-wide or
    1-high plane, which is never weighted). ``group`` consecutive planes are multiplied.
    """

    u_axis: tuple[int, ...]
    v_axis: tuple[int, ...]
    width: tuple[int, ...]
    height: tuple[int, ...]
    offset: tuple[int, ...]
    shifts: tuple[tuple[int, int, int, int], ...]
    group: int
    num_cells: int

    @staticmethod
    def build(sizes: Sequence[tuple[int, int]], axes: Sequence[tuple[int, int]], group: int) -> PlaneLayout:
        """``sizes`` [(H, W)] and ``axes`` [(u_axis, v_axis)] per plane, in table order."""
        if len(sizes) != len(axes) or group < 1 or len(sizes) % group:
            raise ValueError(f"PlaneLayout: {len(sizes)} planes, {len(axes)} axis pairs, groups of {group}")
        offsets, total = [], 0
        for h, w in sizes:
            offsets.append(total)
            total += h * w
        shifts = []
        for h, w in sizes:
            col, row = (1 if w > 1 else 0), (w if h > 1 else 0)
            shifts.append((0, col, row, col + row))
        return PlaneLayout(
            u_axis=tuple(a for a, _ in axes),
            v_axis=tuple(b for _, b in axes),
            width=tuple(w for _, w in sizes),
            height=tuple(h for h, _ in sizes),
            offset=tuple(offsets),
            shifts=tuple(shifts),
            group=group,
            num_cells=total,
        )

    @property
    def num_planes(self) -> int:
        return len(self.u_axis)


def planes_to_table(planes: Sequence[Tensor]) -> Tensor:
    """[sum(H*W), C] channels-last table of [1, C, H, W] planes (differentiable)."""
    channels = planes[0].shape[1]
    return torch.cat([plane.reshape(channels, -1) for plane in planes], 1).t().contiguous()


def table_plane_views(table: Tensor, layout: PlaneLayout) -> list[Tensor]:
    """The [1, C, H, W] planes of a [num_cells, C] table, as views (channels-last strides)."""
    return [table[start : start + h * w].view(h, w, table.shape[1]).permute(2, 0, 1).unsqueeze(0)
            for start, h, w in zip(layout.offset, layout.height, layout.width)]


def shared_table(planes: Sequence[Tensor], layout: PlaneLayout) -> Tensor | None:
    """The [num_cells, C] table the planes are views of, or None when they are not (any more).

    Planes become separate tensors when something replaces their data (``module.to(device)``,
    a user's ``p.data = ...``); the caller then packs them again.
    """
    first = planes[0]
    if first.dim() != 4 or len(planes) != layout.num_planes:
        return None
    channels = first.shape[1]
    storage = first.untyped_storage()
    base = first.storage_offset()
    table = first.new_empty(0).set_(storage, base, (layout.num_cells, channels), (channels, 1))
    if (base + layout.num_cells * channels) * first.element_size() > storage.nbytes():
        return None
    for plane, view in zip(planes, table_plane_views(table, layout)):
        if (plane.untyped_storage().data_ptr() != storage.data_ptr() or plane.shape != view.shape
                or plane.stride() != view.stride() or plane.storage_offset() != view.storage_offset()
                or plane.dtype != view.dtype):
            return None
    return table


def pack_planes(planes: Sequence[Tensor], layout: PlaneLayout) -> list[Tensor]:
    """Copy the planes' values into one new table; its plane views, to become the planes' data."""
    channels = planes[0].shape[1]
    table = planes[0].new_empty(layout.num_cells, channels)
    views = table_plane_views(table, layout)
    with torch.no_grad():
        for view, plane in zip(views, planes):
            view.copy_(plane)
    return views


@dataclass
class _AxisCells:
    """align_corners sampling along one axis: top-left index, fraction, "inside" mask, all [N]."""

    index: Tensor
    frac: Tensor
    inside: Tensor

    @staticmethod
    def of(coord: Tensor, size: int) -> _AxisCells:
        extent = float(size - 1)
        scaled = (coord + 1.0) * (0.5 * extent)
        inside = (scaled > 0) & (scaled < extent)  # border padding: no gradient where clamped
        clamped = scaled.clamp(0.0, extent)
        index = clamped.floor().clamp_(max=max(extent - 1.0, 0.0))
        return _AxisCells(index.long(), clamped - index, inside)


class _PlaneCells:
    """Per-plane corner rows and bilinear weights of N points (axis lookups shared by planes)."""

    def __init__(self, coords: Tensor, layout: PlaneLayout) -> None:
        axes: dict[tuple[int, int], _AxisCells] = {}

        def axis(index: int, size: int) -> _AxisCells:
            if (index, size) not in axes:
                axes[(index, size)] = _AxisCells.of(coords[index], size)
            return axes[(index, size)]

        self.u = [axis(a, w) for a, w in zip(layout.u_axis, layout.width)]
        self.v = [axis(b, h) for b, h in zip(layout.v_axis, layout.height)]
        self.layout = layout
        self._corners: dict[int, Tensor] = {}
        self._weights: dict[int, Tensor] = {}

    def base(self, plane: int) -> Tensor:
        """[N] table row of each point's top-left corner on ``plane``."""
        return self.corners(plane)[:, 0]

    def corners(self, plane: int) -> Tensor:
        """[N, 4] table rows of the 4 corners (top-left, top-right, bottom-left, bottom-right)."""
        if plane not in self._corners:
            layout = self.layout
            base = self.v[plane].index * layout.width[plane] + (self.u[plane].index + layout.offset[plane])
            self._corners[plane] = base.unsqueeze(1) + base.new_tensor(layout.shifts[plane])
        return self._corners[plane]

    def weights(self, plane: int) -> Tensor:
        """[N, 4] bilinear weights of the corners."""
        if plane not in self._weights:
            fu, fv = self.u[plane].frac, self.v[plane].frac
            gu, gv = 1.0 - fu, 1.0 - fv
            self._weights[plane] = torch.stack((gu * gv, fu * gv, gu * fv, fu * fv), 1)
        return self._weights[plane]

    def sample(self, table: Tensor, plane: int) -> Tensor:
        """[N, C] bilinear samples of ``plane``."""
        return F.embedding_bag(self.corners(plane), table, per_sample_weights=self.weights(plane), mode="sum")


def _group_products(cells: _PlaneCells, table: Tensor, layout: PlaneLayout) -> Tensor:
    """[N, groups * C]: each group's planes sampled and multiplied, groups concatenated."""
    products = []
    for first in range(0, layout.num_planes, layout.group):
        product = cells.sample(table, first)
        for plane in range(first + 1, first + layout.group):
            product.mul_(cells.sample(table, plane))
        products.append(product)
    return torch.cat(products, 1)


class _PlaneProductLookup(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table: Tensor, space: Tensor, time: Tensor, layout: PlaneLayout) -> Tensor:
        # embedding_bag's fast forward-only path needs no-grad inputs
        products, coords, cells = _forward(table.detach(), space, time, layout)
        ctx.save_for_backward(table, coords)
        ctx.cells, ctx.layout, ctx.num_space = cells, layout, space.shape[1]
        return products

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):
        table, coords = ctx.saved_tensors
        need_table, need_space, need_time = ctx.needs_input_grad[:3]
        grads = _backward(grad_out, table.detach(), coords, ctx.cells, ctx.layout, ctx.num_space,
                          need_table, need_space, need_time)
        return (*grads, None)


class _SharedTableLookup(torch.autograd.Function):
    """The lookup on planes that are views of one table: no table built, plane gradients as views.

    ``table`` is passed detached (it is the planes' own storage); the planes are the inputs that
    receive gradients, each a view of one [num_cells, C] gradient with the parameters' strides
    (so autograd hands it over without a copy).
    """

    @staticmethod
    def forward(ctx, space: Tensor, time: Tensor, table: Tensor, layout: PlaneLayout, *planes: Tensor) -> Tensor:
        products, coords, cells = _forward(table, space, time, layout)
        # the planes are saved (no copy) so that autograd's version check catches an in-place
        # update between this forward and its backward, which would read the new values
        ctx.save_for_backward(coords, *planes)
        ctx.table, ctx.cells, ctx.layout, ctx.num_space = table, cells, layout, space.shape[1]
        return products

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):
        coords = ctx.saved_tensors[0]
        need_space, need_time = ctx.needs_input_grad[:2]
        need_planes = any(ctx.needs_input_grad[4:])
        grad_table, grad_space, grad_time = _backward(
            grad_out, ctx.table, coords, ctx.cells, ctx.layout, ctx.num_space, need_planes, need_space, need_time)
        plane_grads = table_plane_views(grad_table, ctx.layout) if need_planes else [None] * ctx.layout.num_planes
        return (grad_space, grad_time, None, None, *plane_grads)


def _forward(table: Tensor, space: Tensor, time: Tensor, layout: PlaneLayout
             ) -> tuple[Tensor, Tensor, _PlaneCells | None]:
    """(products [N, groups * C], coordinates to keep for backward, the torch path's cells or None).

    The compiled kernel (plane_kernel.py) runs where it can and keeps coordinates [N, D]; the
    torch path keeps them [D, N] with the corner rows and weights (about 200 small ops to
    rebuild; the samples are recomputed in backward, one cheap embedding_bag each).
    """
    reason = plane_kernel.unusable_reason(table, space.dtype)
    if reason is None:
        coords = torch.cat((space, time), 1).contiguous()  # [N, D]
        return plane_kernel.lookup_forward(table, coords, layout), coords, None
    plane_kernel.log_fallback_once(reason)
    coords = torch.cat((space, time), 1).t().contiguous()  # [D, N]
    cells = _PlaneCells(coords, layout)
    return _group_products(cells, table, layout), coords, cells


def _backward(grad_out: Tensor, table: Tensor, coords: Tensor, cells: _PlaneCells | None, layout: PlaneLayout,
              num_space: int, need_table: bool, need_space: bool, need_time: bool
              ) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """(grad_table, grad_space [N, S], grad_time [N, T]) by the path ``_forward`` took."""
    if cells is not None:
        return _lookup_backward(grad_out, table, coords, cells, num_space, need_table, need_space, need_time)
    dims = coords.shape[1]
    want_axis = [need_space if axis < num_space else need_time for axis in range(dims)]
    grad_table, grad_coords = plane_kernel.lookup_backward(table, coords, layout, grad_out, want_axis, need_table)
    grad_space = grad_coords[:, :num_space] if need_space else None
    grad_time = grad_coords[:, num_space:] if need_time else None
    return grad_table, grad_space, grad_time


def _lookup_backward(grad_out: Tensor, table: Tensor, coords: Tensor, cells: _PlaneCells, num_space: int,
                     need_table: bool, need_space: bool, need_time: bool
                     ) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """(grad_table [num_cells, C], grad_space [N, S], grad_time [N, T]) of the group products.

    ``cells``: the forward's corner rows and weights of the points ``coords`` [D, N].
    """
    layout = cells.layout
    channels = table.shape[1]
    grad_table = table.new_zeros(layout.num_cells, channels) if need_table else None
    grad_coords = coords.new_zeros(coords.shape) if (need_space or need_time) else None

    def wants(axis: int) -> bool:
        return need_space if axis < num_space else need_time

    for group_index, first in enumerate(range(0, layout.num_planes, layout.group)):
        planes = range(first, first + layout.group)
        grad_product = grad_out[:, group_index * channels : (group_index + 1) * channels].contiguous()
        samples = [cells.sample(table, plane) for plane in planes]
        for plane, grad_sample in zip(planes, _product_grads(grad_product, samples)):
            if need_table:
                _add_table_grad(grad_table, grad_sample, cells, plane)
            if grad_coords is not None:
                _add_coordinate_grads(grad_coords, grad_sample, table, cells, plane, wants)

    grad_space = grad_coords[:num_space].t() if need_space else None
    grad_time = grad_coords[num_space:].t() if need_time else None
    return grad_table, grad_space, grad_time


def _product_grads(grad_product: Tensor, samples: Sequence[Tensor]) -> list[Tensor]:
    """d(sum grad * prod_k s_k) / d s_k = grad * prod_{j != k} s_j, via prefix and suffix products
    (no division, so zeros are exact)."""
    count = len(samples)
    suffixes: list[Tensor | None] = [None] * count
    running: Tensor | None = None
    for k in range(count - 1, 0, -1):
        running = samples[k] if running is None else running * samples[k]
        suffixes[k - 1] = running
    grads = []
    prefix = grad_product
    for k in range(count):
        grads.append(prefix if suffixes[k] is None else prefix * suffixes[k])
        if k < count - 1:
            prefix = prefix * samples[k]
    return grads


def _add_coordinate_grads(
    grad_coords: Tensor, grad_sample: Tensor, table: Tensor, cells: _PlaneCells, plane: int, wants
) -> None:
    """grad_coords[axis] += d(sample) / d(coordinate) . grad_sample for the plane's two axes.

    d sample / d fu is the sample taken with the weights' derivative (-gv, gv, -fv, fv) (and
    (-gu, -fu, gu, fu) for fv); the chain rule adds (size - 1) / 2, and 0 where clamped.
    """
    layout = cells.layout
    corners = cells.corners(plane)
    for own, other, axis, size, along_u in (
        (cells.u[plane], cells.v[plane], layout.u_axis[plane], layout.width[plane], True),
        (cells.v[plane], cells.u[plane], layout.v_axis[plane], layout.height[plane], False),
    ):
        if not wants(axis):
            continue
        g, f = 1.0 - other.frac, other.frac
        d_weights = torch.stack((-g, g, -f, f) if along_u else (-g, -f, g, f), 1)
        derivative = F.embedding_bag(corners, table, per_sample_weights=d_weights, mode="sum")
        grad_frac = torch.linalg.vecdot(derivative, grad_sample)
        grad_coords[axis] += grad_frac * (0.5 * (size - 1)) * own.inside


def _add_table_grad(grad_table: Tensor, grad_sample: Tensor, cells: _PlaneCells, plane: int) -> None:
    """grad_table[corner_c(n)] += weight_c(n) * grad_sample[n], summed over points n and corners c.

    Points are ordered by top-left cell once; every corner is then one bag-per-cell
    ``embedding_bag`` over the sample gradients in that order, added at the corner's row offset.
    Planes with more than 4 cells per point take ``index_add_`` of the corners instead.
    """
    layout = cells.layout
    start, cell_count = layout.offset[plane], layout.width[plane] * layout.height[plane]
    if INDEX_ADD_CELLS_PER_POINT * grad_sample.shape[0] < cell_count:
        # Few points on a large plane: scatter the 4 weighted corners (O(N C)) instead of one
        # bag per cell and corner (O(cells C), which made large 4DGS planes slow at small N).
        corners, weights = cells.corners(plane), cells.weights(plane)
        for corner in range(4):
            grad_table.index_add_(0, corners[:, corner], grad_sample * weights[:, corner : corner + 1])
        return
    base = cells.base(plane) - start
    order = torch.argsort(base)
    counts = torch.bincount(base, minlength=cell_count)
    offsets = torch.cumsum(counts, 0) - counts
    sorted_weights = cells.weights(plane).index_select(0, order).t().contiguous()
    region = grad_table[start : start + cell_count]
    for corner, shift in enumerate(layout.shifts[plane]):
        per_cell = F.embedding_bag(order, grad_sample, offsets, per_sample_weights=sorted_weights[corner], mode="sum")
        region[shift:] += per_cell[: cell_count - shift]


def shared_plane_product_lookup(planes: Sequence[Tensor], table: Tensor, layout: PlaneLayout, space: Tensor,
                                time: Tensor | None = None) -> Tensor:
    """``plane_product_lookup`` on planes that are views of ``table`` (see ``shared_table``).

    Same values and gradients; the per-call table copy and the gradient's transposition back to
    the planes are gone (the fixed cost that made small point counts slow).
    """
    if time is None:
        time = space.new_zeros(space.shape[0], 0)
    if space.shape[0] == 0:
        return space.new_zeros(0, (layout.num_planes // layout.group) * table.shape[1])
    return _SharedTableLookup.apply(space, time.to(space.dtype), table.detach(), layout, *planes)


def plane_product_lookup(table: Tensor, layout: PlaneLayout, space: Tensor, time: Tensor | None = None) -> Tensor:
    """[N, (P / group) * C] products of bilinear plane samples (see the module docstring).

    Args:
        table: [sum(H*W), C] from ``planes_to_table``.
        layout: the planes' ``PlaneLayout``.
        space: [N, S] coordinates in [-1, 1] (axes 0..S-1).
        time: [N, T] further coordinates (axes S..S+T-1), kept apart so that their gradient is
            computed only when they require one.
    """
    if time is None:
        time = space.new_zeros(space.shape[0], 0)
    if space.shape[0] == 0:
        return space.new_zeros(0, (layout.num_planes // layout.group) * table.shape[1])
    return _PlaneProductLookup.apply(table, space, time.to(space.dtype), layout)
