"""The 4DGS deformation module and the non-raster part of a step: ours vs 4DGS's recipe, by size.

    python benchmarks/deformation.py                               # 3 configs x 2k..100k Gaussians
    python benchmarks/deformation.py --configs lego --sizes 2000 20000 --repeats 9

Configs (read with train.py's parser): ``lego`` = arguments/dnerf/lego.py (2 levels, 32 channels,
width 64), ``nvidia`` = arguments/nvidia/default.py (3 levels, 16 channels, width 128), ``bare`` =
4DGS's ModelHiddenParams defaults (4 levels up to 8x, 32 channels: what 4DGS runs without a
config). ``PlainDeformNetwork`` below is 4DGS's module recipe (grid_sample per plane, same
state-dict keys); both modules share one state dict and the same inputs. Two measures per size:

- deformation: forward + backward of a scalar loss over every output the config's heads change
  (gradients reach the means, as in training, and every weight);
- step: the non-raster part of a fine-stage step: the deformation's forward + backward, the
  HexPlane regularisers (the config's weights) forward + backward, and the Adam step over every
  parameter (the deformation's and the Gaussians' means/scales/rotations/opacities/SH) -- ours
  with our regularisers and optimizer (fused gradient, fused Adam), the recipe with 4DGS's
  formulas through autograd and torch's default Adam.

Calls alternate between the two sides so machine load affects both alike; medians are printed
with the ratio recipe / ours (above 1: ours is faster). ``PlainDeformNetwork`` is also the test
oracle of the deformation.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
import types
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(0, str(REPO_ROOT))
from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()  # before torch: OpenMP waits and the allocator (baselines/thread_policy.py)

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch import nn  # noqa: E402

from baselines.fourdgs.deformation import DeformNetwork  # noqa: E402
from baselines.fourdgs.regularization import (  # noqa: E402
    hexplane_regularization,
    hexplane_regularization_reference,
)
from benchmarks.machine import cpu_model, load_average  # noqa: E402
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
CONFIGS = {"lego": "arguments/dnerf/lego.py", "nvidia": "arguments/nvidia/default.py", "bare": None}
DEFAULT_SIZES = [2_000, 5_000, 10_000, 20_000, 100_000]


def config_hidden(name: str) -> types.SimpleNamespace:
    """ModelHiddenParams of a named config, as train.py would parse them."""
    from arguments import parse_train_args

    path = CONFIGS[name]
    args = parse_train_args(["-s", "unused"] + (["--configs", str(REPO_ROOT / path)] if path else []))
    return types.SimpleNamespace(**vars(args.hidden))


def _inputs(count: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    means = (torch.rand(count, 3, generator=generator) * 2 - 1) * 1.5
    log_scales = torch.randn(count, 3, generator=generator) * 0.3 - 4
    rotations = torch.randn(count, 4, generator=generator)
    opacity = torch.randn(count, 1, generator=generator)
    shs = torch.randn(count, 16, 3, generator=generator) * 0.1
    times = torch.full((count, 1), 0.37)
    return means, log_scales, rotations, opacity, shs, times


def _time_call(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


class _Side:
    """One side of the comparison: a module, its Gaussians and optimizer, and the two timed calls."""

    def __init__(self, module: nn.Module, ours: bool, gaussians: list[torch.Tensor], times: torch.Tensor,
                 hidden: types.SimpleNamespace) -> None:
        self.module, self.ours, self.times, self.hidden = module, ours, times, hidden
        self.gaussians = [nn.Parameter(g.clone()) for g in gaussians]
        params = [p for p in module.parameters() if p.requires_grad] + self.gaussians
        # ours: what GaussianModel.training_setup builds; the recipe: 4DGS's torch.optim.Adam
        self.optimizer = torch.optim.Adam(params, lr=1e-6, eps=1e-15, fused=True if ours else None)

    def _loss(self) -> torch.Tensor:
        means, log_scales, rotations, opacity, shs = self.gaussians
        if self.ours:
            out = self.module(GaussianState(means, log_scales, rotations, opacity, shs), self.times)
            outputs = (out.means, out.log_scales, out.rotations, out.opacity_logits, out.shs)
        else:
            outputs = self.module(means, log_scales, rotations, opacity, shs, self.times)
        return sum(o.sum() for o in outputs)

    def _regularisation(self) -> torch.Tensor:
        h = self.hidden
        grids = self.module.deformation_net.grid.grids
        regularization = hexplane_regularization if self.ours else hexplane_regularization_reference
        return regularization(grids, h.time_smoothness_weight, h.l1_time_planes, h.plane_tv_weight)

    def deformation(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        self._loss().backward()

    def step(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        (self._loss() + self._regularisation()).backward()
        self.optimizer.step()


def run(configs: list[str], sizes: list[int], repeats: int, warmup: int) -> None:
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {cpu_model()}, load {load_average()}")
    print("| config | Gaussians | deformation: recipe ms | ours ms | recipe / ours | step: recipe ms | ours ms "
          "| recipe / ours |\n|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in configs:
        hidden = config_hidden(name)
        torch.manual_seed(0)
        ours_module = DeformNetwork(hidden)
        plain_module = PlainDeformNetwork(hidden)
        plain_module.load_state_dict({k: v.contiguous() for k, v in ours_module.state_dict().items()}, strict=True)
        generator = torch.Generator().manual_seed(0)
        for count in sizes:
            *gaussians, times = _inputs(count, generator)
            sides = {"plain": _Side(plain_module, False, gaussians, times, hidden),
                     "ours": _Side(ours_module, True, gaussians, times, hidden)}
            medians = {}
            for measure in ("deformation", "step"):
                samples: dict[str, list[float]] = {"plain": [], "ours": []}
                for index in range(warmup + repeats):
                    for side_name, side in sides.items():
                        elapsed = _time_call(getattr(side, measure))
                        if index >= warmup:
                            samples[side_name].append(elapsed)
                for side_name in sides:
                    medians[measure, side_name] = statistics.median(samples[side_name]) * 1e3
            cells = []
            for measure in ("deformation", "step"):
                plain_ms, ours_ms = medians[measure, "plain"], medians[measure, "ours"]
                cells += [f"{plain_ms:.1f}", f"{ours_ms:.1f}", f"{plain_ms / ours_ms:.2f}x"]
            print(f"| {name} | {count} | " + " | ".join(cells) + " |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--sizes", type=int, nargs="+", default=DEFAULT_SIZES)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"# command: python benchmarks/deformation.py {' '.join(sys.argv[1:])}")
    run(args.configs, args.sizes, args.repeats, args.warmup)


if __name__ == "__main__":
    main()
