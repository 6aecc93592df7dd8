"""Forward+backward time of the 4DGS deformation module: ours vs 4DGS's layer-by-layer recipe.

    python benchmarks/deformation.py                      # 20k and 100k Gaussians, lego config
    python benchmarks/deformation.py --sizes 20000 --repeats 15 --threads 2

Config (4DGS arguments/dnerf/lego.py over dnerf_default.py): kplanes resolution [64, 64, 64, 25],
32 channels, multires [1, 2], net_width 64, defor_depth 0; ModelHiddenParams defaults otherwise
(no_do and no_dshs True, so the position, scale and rotation heads run). Both modules share one
state dict and the same inputs; each timed call is deformation forward + backward of a scalar
loss over all outputs (gradients flow to the means, as in training, and to every weight).
Calls alternate between the two modules so machine load affects both alike; medians are
printed with the ratio plain / ours. ``PlainDeformNetwork`` is also the test oracle.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
import types
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()  # before torch: passive OpenMP waits unless OMP_WAIT_POLICY is set

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch import nn  # noqa: E402

from baselines.fourdgs.deformation import DeformNetwork  # noqa: E402
from baselines.fourdgs.state import GaussianState  # noqa: E402

LEGO_HIDDEN = dict(
    kplanes_config={"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 32,
                    "resolution": [64, 64, 64, 25]},
    multires=[1, 2],
    defor_depth=0,
    net_width=64,
    bounds=1.6,
)


# --------------------------------------------------------------------------------------------
# 4DGS's recipe, module by module (scene/hexplane.py, scene/deformation.py), same parameter names.
def _positional_encoding(values: torch.Tensor, frequencies: torch.Tensor) -> torch.Tensor:
    scaled = (values.unsqueeze(-1) * frequencies).flatten(-2)
    return torch.cat([values, scaled.sin(), scaled.cos()], -1)


class PlainHexPlane(nn.Module):
    def __init__(self, bounds: float, planeconfig: dict, multires: list[int]) -> None:
        super().__init__()
        self.aabb = nn.Parameter(torch.tensor([[bounds] * 3, [-bounds] * 3]), requires_grad=False)
        self.grids = nn.ModuleList()
        for multiplier in multires:
            reso = [r * multiplier for r in planeconfig["resolution"][:3]] + planeconfig["resolution"][3:]
            planes = nn.ParameterList()
            for axes in itertools.combinations(range(4), 2):
                plane = torch.empty([1, planeconfig["output_coordinate_dim"]] + [reso[a] for a in axes[::-1]])
                planes.append(nn.Parameter(plane.fill_(1.0) if 3 in axes else plane.uniform_(0.1, 0.5)))
            self.grids.append(planes)

    def forward(self, pts: torch.Tensor, timestamps: torch.Tensor) -> torch.Tensor:
        pts = (pts - self.aabb[0]) * (2.0 / (self.aabb[1] - self.aabb[0])) - 1.0
        pts = torch.cat((pts, timestamps), dim=-1).reshape(-1, 4)
        features = []
        for planes in self.grids:
            product = 1.0
            for plane, axes in zip(planes, itertools.combinations(range(4), 2)):
                coords = pts[..., axes].view(1, 1, -1, 2)
                sample = F.grid_sample(plane, coords, align_corners=True, mode="bilinear", padding_mode="border")
                sample = sample.view(1, plane.shape[1], -1).transpose(-1, -2).squeeze()
                product = product * sample.view(-1, plane.shape[1])
            features.append(product)
        return torch.cat(features, dim=-1)


def _plain_head(width: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out))


class PlainDeformation(nn.Module):
    def __init__(self, args, D: int, W: int) -> None:
        super().__init__()
        self.args = args
        self.grid = PlainHexPlane(args.bounds, args.kplanes_config, args.multires)
        feat_dim = args.kplanes_config["output_coordinate_dim"] * len(args.multires)
        layers = [nn.Linear(feat_dim, W)]
        for _ in range(D - 1):
            layers += [nn.ReLU(), nn.Linear(W, W)]
        self.feature_out = nn.Sequential(*layers)
        self.pos_deform = _plain_head(W, 3)
        self.scales_deform = _plain_head(W, 3)
        self.rotations_deform = _plain_head(W, 4)
        self.opacity_deform = _plain_head(W, 1)
        self.shs_deform = _plain_head(W, 16 * 3)

    def forward(self, point_emb, scales_emb, rotations_emb, opacity, shs, time):
        hidden = self.feature_out(self.grid(point_emb[:, :3], time[:, :1]))
        mask = torch.ones_like(opacity[:, 0]).unsqueeze(-1)
        a = self.args
        pts = point_emb[:, :3] if a.no_dx else point_emb[:, :3] * mask + self.pos_deform(hidden)
        scales = scales_emb[:, :3] if a.no_ds else scales_emb[:, :3] * mask + self.scales_deform(hidden)
        if a.no_dr:
            rotations = rotations_emb[:, :4]
        elif a.apply_rotation:
            q1, q2 = rotations_emb[:, :4], self.rotations_deform(hidden)
            w = q1[:, 0] * q2[:, 0] - q1[:, 1] * q2[:, 1] - q1[:, 2] * q2[:, 2] - q1[:, 3] * q2[:, 3]
            x = q1[:, 0] * q2[:, 1] + q1[:, 1] * q2[:, 0] + q1[:, 2] * q2[:, 3] - q1[:, 3] * q2[:, 2]
            y = q1[:, 0] * q2[:, 2] - q1[:, 1] * q2[:, 3] + q1[:, 2] * q2[:, 0] + q1[:, 3] * q2[:, 1]
            z = q1[:, 0] * q2[:, 3] + q1[:, 1] * q2[:, 2] - q1[:, 2] * q2[:, 1] + q1[:, 3] * q2[:, 0]
            q3 = torch.stack((w, x, y, z), dim=1)
            rotations = q3 / torch.norm(q3, dim=1, keepdim=True)
        else:
            rotations = rotations_emb[:, :4] + self.rotations_deform(hidden)
        opacity = opacity[:, :1] if a.no_do else opacity[:, :1] * mask + self.opacity_deform(hidden)
        if a.no_dshs:
            out_shs = shs
        else:
            out_shs = shs * mask.unsqueeze(-1) + self.shs_deform(hidden).reshape([shs.shape[0], 16, 3])
        return pts, scales, rotations, opacity, out_shs


class PlainDeformNetwork(nn.Module):
    """4DGS's deform_network recipe (same state-dict keys as ``DeformNetwork``)."""

    def __init__(self, args) -> None:
        super().__init__()
        self.timenet = nn.Sequential(
            nn.Linear(2 * args.timebase_pe + 1, args.timenet_width), nn.ReLU(),
            nn.Linear(args.timenet_width, args.timenet_output),
        )
        self.deformation_net = PlainDeformation(args, D=args.defor_depth, W=args.net_width)
        self.register_buffer("time_poc", torch.FloatTensor([2**i for i in range(args.timebase_pe)]))
        self.register_buffer("pos_poc", torch.FloatTensor([2**i for i in range(args.posebase_pe)]))
        self.register_buffer("rotation_scaling_poc", torch.FloatTensor([2**i for i in range(args.scale_rotation_pe)]))
        self.register_buffer("opacity_poc", torch.FloatTensor([2**i for i in range(args.opacity_pe)]))

    def forward(self, point, scales, rotations, opacity, shs, times_sel):
        return self.deformation_net(
            _positional_encoding(point, self.pos_poc),
            _positional_encoding(scales, self.rotation_scaling_poc),
            _positional_encoding(rotations, self.rotation_scaling_poc),
            opacity, shs, times_sel,
        )


def hidden_args(**overrides) -> types.SimpleNamespace:
    """4DGS ModelHiddenParams defaults with ``overrides``."""
    from baselines.fourdgs.deformation import HIDDEN_DEFAULTS

    values = {**HIDDEN_DEFAULTS, **overrides}
    values["kplanes_config"] = dict(values["kplanes_config"])
    return types.SimpleNamespace(**values)


# --------------------------------------------------------------------------------------------
def _inputs(count: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    means = (torch.rand(count, 3, generator=generator) * 2 - 1) * 1.5
    log_scales = torch.randn(count, 3, generator=generator) * 0.3 - 4
    rotations = torch.randn(count, 4, generator=generator)
    opacity = torch.randn(count, 1, generator=generator)
    shs = torch.randn(count, 16, 3, generator=generator) * 0.1
    times = torch.full((count, 1), 0.37)
    return means, log_scales, rotations, opacity, shs, times


def _time_call(fn) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - wall, time.process_time() - cpu


def run(sizes: list[int], repeats: int, warmup: int) -> None:
    torch.manual_seed(0)
    args = hidden_args(**LEGO_HIDDEN)
    ours = DeformNetwork(args)
    plain = PlainDeformNetwork(args)
    plain.load_state_dict(ours.state_dict(), strict=True)
    generator = torch.Generator().manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; config: lego (multires [1, 2], "
          f"resolution [64, 64, 64, 25], 32 channels, net_width 64, defor_depth 0)")
    for count in sizes:
        means, log_scales, rotations, opacity, shs, times = _inputs(count, generator)
        means.requires_grad_(True)

        def step_ours():
            out = ours(GaussianState(means, log_scales, rotations, opacity, shs), times)
            (out.means.sum() + out.log_scales.sum() + out.rotations.sum()).backward()

        def step_plain():
            pts, scales, rots, _, _ = plain(means, log_scales, rotations, opacity, shs, times)
            (pts.sum() + scales.sum() + rots.sum()).backward()

        for _ in range(warmup):
            step_ours()
            step_plain()
        timings: dict[str, list[tuple[float, float]]] = {"ours": [], "plain": []}
        for _ in range(repeats):
            timings["ours"].append(_time_call(step_ours))
            timings["plain"].append(_time_call(step_plain))
        ours_ms, ours_cpu = (statistics.median(t[i] for t in timings["ours"]) * 1e3 for i in (0, 1))
        plain_ms, plain_cpu = (statistics.median(t[i] for t in timings["plain"]) * 1e3 for i in (0, 1))
        print(f"N={count:>7}: ours {ours_ms:8.1f} ms   plain 4DGS recipe {plain_ms:8.1f} ms   "
              f"plain/ours {plain_ms / ours_ms:5.2f}x   (median of {repeats}, fwd+bwd; process CPU time "
              f"ours {ours_cpu:.0f} ms, plain {plain_cpu:.0f} ms)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20_000, 100_000])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    run(args.sizes, args.repeats, args.warmup)


if __name__ == "__main__":
    main()
