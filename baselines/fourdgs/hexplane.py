"""HexPlane feature field with 4DGS semantics and parameter names (scene/hexplane.py).

A level holds six planes, one per pair of the 4 coordinates (x, y, z, t) in the order
``itertools.combinations(range(4), 2)``: xy, xz, xt, yz, yt, zt. The plane for the pair (a, b)
has shape [1, C, res[b], res[a]], so ``grid_sample`` coordinates (u, v) = (coord_a, coord_b).
A point's feature at one level is the elementwise product of its six bilinear samples
(``align_corners=True``, border padding); levels are concatenated. Spatial resolutions are
multiplied by the level's multiplier, the time resolution is not. Spatial planes start
uniform in [0.1, 0.5], planes containing time start at 1, so at initialisation the feature
does not depend on t.

Coordinates follow 4DGS exactly: points are mapped with ``(p - aabb[0]) * 2 / (aabb[1] -
aabb[0]) - 1`` where ``aabb = [[max], [min]]`` (so max -> -1, min -> +1), and times are used
as given (t in [0, 1] addresses the upper half of the time axis).

Speed: the lookups of all planes of all levels run as one ``plane_lookup`` call (a channels-last
table and ``embedding_bag`` instead of 6 x levels ``grid_sample`` calls, whose CPU backward
dominates a 4DGS training step). Values and gradients equal ``grid_sample``'s to float rounding.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from baselines.fourdgs.plane_lookup import (
    PlaneLayout,
    pack_planes,
    plane_product_lookup,
    planes_to_table,
    shared_plane_product_lookup,
    shared_table,
)
from baselines.fourdgs.regularization import hexplane_regularization

PLANE_AXES: tuple[tuple[int, int], ...] = tuple(itertools.combinations(range(4), 2))


def sample_plane(plane: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear sample of a [1, C, H, W] plane at (u, v) in [-1, 1] -> [N, C].

    Equals ``F.grid_sample(plane, grid, mode='bilinear', padding_mode='border',
    align_corners=True)`` with grid = stack(u, v) (u indexes W, v indexes H).
    """
    layout = PlaneLayout.build([tuple(plane.shape[-2:])], [(0, 1)], 1)
    return plane_product_lookup(planes_to_table([plane]), layout, torch.stack((u, v), 1))


# --------------------------------------------------------------------------------------------
def _init_level(config: Mapping[str, Any], a: float = 0.1, b: float = 0.5) -> nn.ParameterList:
    """Six planes of one level: uniform(a, b), time planes set to 1 (4DGS's init_grid_param)."""
    resolution = config["resolution"]
    planes = nn.ParameterList()
    for axes in PLANE_AXES:
        shape = [1, config["output_coordinate_dim"]] + [resolution[i] for i in axes[::-1]]
        plane = nn.Parameter(torch.empty(shape))
        if 3 in axes:
            nn.init.ones_(plane)
        else:
            nn.init.uniform_(plane, a=a, b=b)
        planes.append(plane)
    return planes


def _check_plane_config(planeconfig: Mapping[str, Any], multires: Sequence[int]) -> None:
    for key in ("grid_dimensions", "input_coordinate_dim", "output_coordinate_dim", "resolution"):
        if key not in planeconfig:
            raise ValueError(f"kplanes_config: missing key {key!r}")
    if planeconfig["grid_dimensions"] != 2:
        raise ValueError(f"kplanes_config['grid_dimensions'] must be 2, got {planeconfig['grid_dimensions']}")
    if planeconfig["input_coordinate_dim"] != 4:
        raise ValueError(
            f"kplanes_config['input_coordinate_dim'] must be 4 (x, y, z, t), got {planeconfig['input_coordinate_dim']}"
        )
    resolution = list(planeconfig["resolution"])
    if len(resolution) != 4 or any(int(r) != r or r < 1 for r in resolution):
        raise ValueError(f"kplanes_config['resolution'] must be 4 positive integers, got {resolution}")
    channels = planeconfig["output_coordinate_dim"]
    if int(channels) != channels or channels < 1:
        raise ValueError(f"kplanes_config['output_coordinate_dim'] must be a positive integer, got {channels}")
    if len(multires) == 0 or any(int(m) != m or m < 1 for m in multires):
        raise ValueError(f"multires must be a non-empty list of positive integers, got {list(multires)}")


class HexPlaneField(nn.Module):
    """Multi-resolution HexPlane: ``forward(pts [N,3], timestamps [N,1]) -> [N, feat_dim]``.

    Args:
        bounds: initial half-size of the box (aabb = [[b,b,b], [-b,-b,-b]]) until ``set_aabb``.
        planeconfig: 4DGS ``kplanes_config`` (grid_dimensions 2, input_coordinate_dim 4,
            output_coordinate_dim C, resolution [X, Y, Z, T]).
        multires: spatial resolution multipliers, one level each.
    """

    def __init__(self, bounds: float, planeconfig: Mapping[str, Any], multires: Sequence[int]) -> None:
        super().__init__()
        _check_plane_config(planeconfig, multires)
        bounds = float(bounds)
        self.aabb = nn.Parameter(
            torch.tensor([[bounds] * 3, [-bounds] * 3], dtype=torch.float32), requires_grad=False
        )
        self.grid_config = [dict(planeconfig)]
        self.multiscale_res_multipliers = [int(m) for m in multires]
        self.concat_features = True
        self.grids = nn.ModuleList()
        self.feat_dim = 0
        for multiplier in self.multiscale_res_multipliers:
            config = dict(self.grid_config[0])
            resolution = list(config["resolution"])
            config["resolution"] = [r * multiplier for r in resolution[:3]] + resolution[3:]
            level = _init_level(config)
            self.feat_dim += level[-1].shape[1]
            self.grids.append(level)
        # Table layout of all planes: levels in order, the 6 planes of a level multiplied.
        self.layout = PlaneLayout.build(
            [tuple(p.shape[-2:]) for level in self.grids for p in level],
            list(PLANE_AXES) * len(self.grids),
            len(PLANE_AXES),
        )
        self.pack_planes()

    def _planes(self) -> list[nn.Parameter]:
        return [plane for level in self.grids for plane in level]

    def pack_planes(self) -> None:
        """Make the plane parameters views of one channels-last table (values unchanged).

        The lookup then reads the table in place: no per-call copy of every plane, no transposed
        copy of their gradients (see plane_lookup.py). Parameters keep their identity, names and
        shapes (4DGS's state dict); only their strides are channels-last. Called again by
        ``forward`` whenever something gave the planes separate storage (``.to(device)``).
        """
        planes = self._planes()
        for plane, view in zip(planes, pack_planes(planes, self.layout)):
            plane.data = view

    @property
    def get_aabb(self) -> tuple[Tensor, Tensor]:
        """(xyz_max [3], xyz_min [3]), 4DGS's property name."""
        return self.aabb[0], self.aabb[1]

    def set_aabb(self, xyz_max: Any, xyz_min: Any) -> None:
        """Set the box the spatial coordinates are normalised with (in place, same device)."""
        box = torch.stack(
            [torch.as_tensor(xyz_max, dtype=torch.float32).reshape(-1),
             torch.as_tensor(xyz_min, dtype=torch.float32).reshape(-1)]
        )
        if box.shape != (2, 3):
            raise ValueError(f"set_aabb: xyz_max and xyz_min must have 3 values each, got {list(box.shape)}")
        if not torch.isfinite(box).all():
            raise ValueError(f"set_aabb: non-finite bounds {box.tolist()}")
        flat = (box[0] - box[1]) == 0
        if flat.any():
            axes = [a for a, f in zip("xyz", flat.tolist()) if f]
            raise ValueError(f"set_aabb: empty extent along axis {', '.join(axes)} (max == min)")
        with torch.no_grad():
            self.aabb.copy_(box.to(self.aabb.device, self.aabb.dtype))

    def normalize(self, pts: Tensor) -> Tensor:
        """Map points into the plane coordinates (4DGS's normalize_aabb)."""
        return (pts - self.aabb[0]) * (2.0 / (self.aabb[1] - self.aabb[0])) - 1.0

    def forward(self, pts: Tensor, timestamps: Tensor) -> Tensor:
        if pts.dim() != 2 or pts.shape[1] != 3:
            raise ValueError(f"HexPlaneField: pts must be [N, 3], got {list(pts.shape)}")
        if timestamps.shape != (pts.shape[0], 1):
            raise ValueError(
                f"HexPlaneField: timestamps must be [N, 1] = [{pts.shape[0]}, 1], got {list(timestamps.shape)}"
            )
        if not bool(torch.isfinite(pts).all()):
            raise ValueError("HexPlaneField: non-finite point coordinates (NaN or inf in the means)")
        if not bool(torch.isfinite(timestamps).all()):
            raise ValueError("HexPlaneField: non-finite timestamps")
        if pts.shape[0] == 0:
            return pts.new_zeros(0, self.feat_dim)
        planes = self._planes()
        table = shared_table(planes, self.layout)
        if table is None:
            self.pack_planes()
            table = shared_table(planes, self.layout)
        return shared_plane_product_lookup(planes, table, self.layout, self.normalize(pts), timestamps)

    def compute_regulation(
        self, time_smoothness_weight: float, l1_time_planes_weight: float, plane_tv_weight: float
    ) -> Tensor:
        """4DGS's plane regularisers (see ``regularization.py``)."""
        return hexplane_regularization(
            self.grids, time_smoothness_weight, l1_time_planes_weight, plane_tv_weight
        )
