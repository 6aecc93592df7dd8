"""A small example plugin exercising every capability the ReFlow plugin needs from the host.

- trains on neighbouring frame PAIRS (select_batch);
- adds feature channels to the render pass: a per-Gaussian "dynamic" flag and each Gaussian's
  screen displacement towards the other view of the pair, read from that view's projection
  (extra_features), i.e. a one-pass flow-like map;
- evaluates the deformation of the same Gaussians at another time (model.deform);
- replaces the initial cloud and the deformation module (initial_point_cloud, build_model);
- adds a per-Gaussian buffer that densification keeps in step (on_model_created, post_densify);
- freezes the deformation network during a warm-up at the start of the fine stage;
- adds its own config group and checkpointed state.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
import torch
from torch import Tensor, nn

from arguments import param
from baselines.data import PointCloud
from baselines.fourdgs.deformation import DeformNetwork
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.plugins import Plugin
from baselines.fourdgs.state import GaussianState


@dataclass
class ToyParams:
    toy_warmup_iterations: int = param(3, "fine-stage iterations with the deformation frozen")
    toy_dynamic_weight: float = param(0.0, "weight of a loss on the rendered dynamic map")
    toy_init_points: int = param(300, "points of the plugin's own initial cloud")


class CountingDeformation(nn.Module):
    """Wraps the 4DGS deformation network and counts forward calls (a replaced deformation)."""

    def __init__(self, inner: DeformNetwork) -> None:
        super().__init__()
        self.inner = inner
        self.calls = 0

    def forward(self, state: GaussianState, times: Tensor, buffers: Mapping[str, Tensor] | None = None) -> GaussianState:
        self.calls += 1
        return self.inner(state, times, buffers)

    def get_mlp_parameters(self) -> list[nn.Parameter]:
        return self.inner.get_mlp_parameters()

    def get_grid_parameters(self) -> list[nn.Parameter]:
        return self.inner.get_grid_parameters()

    def set_aabb(self, xyz_max: Any, xyz_min: Any) -> None:
        self.inner.set_aabb(xyz_max, xyz_min)

    def compute_regulation(self, *weights: float) -> Tensor:
        return self.inner.compute_regulation(*weights)


class ToyPairPlugin(Plugin):
    name = "toy_pairs"
    components = ("pairs", "dynamic_channel", "warmup_freeze", "custom_init", "custom_deformation")
    param_groups = {"ToyParams": ToyParams}

    def __init__(self, params=None, enabled=None) -> None:
        super().__init__(params, enabled)
        self.toy: ToyParams = self.params.get("ToyParams", ToyParams())
        self.calls: Counter[str] = Counter()
        self.generator = torch.Generator().manual_seed(1234)
        self.pairs: list[tuple[int, int]] = []
        self.deformation_checked = False
        self.buffer_sizes_ok = True

    def initial_point_cloud(self, ctx):
        if not self.is_enabled("custom_init"):
            return None
        rng = np.random.default_rng(0)
        n = self.toy.toy_init_points
        base = ctx.point_cloud.points
        lo, hi = base.min(0), base.max(0)
        points = (lo + rng.random((n, 3)) * (hi - lo)).astype(np.float32)
        return PointCloud(points=points, colors=rng.random((n, 3)).astype(np.float32))

    def build_model(self, ctx):
        if not self.is_enabled("custom_deformation"):
            return None
        return GaussianModel(ctx.args.model.sh_degree, ctx.args.hidden,
                             deformation=CountingDeformation(DeformNetwork(ctx.args.hidden)))

    def on_model_created(self, ctx) -> None:
        n = ctx.model.num_gaussians
        flags = (torch.arange(n, device=ctx.model.device) % 2).float().unsqueeze(1)
        ctx.model.register_gaussian_buffer("is_dynamic", flags)

    def on_load(self, ctx, point_cloud_dir) -> None:
        # A 4DGS folder has no plugin buffers (ours restores them): create what is missing.
        self.calls["on_load"] += 1
        if "is_dynamic" not in ctx.model.gaussian_buffers:
            self.on_model_created(ctx)

    def on_stage_start(self, ctx) -> None:
        self.calls[f"stage_start_{ctx.stage}"] += 1
        if ctx.stage == "fine" and self.is_enabled("warmup_freeze"):
            ctx.model.freeze(["deformation", "grid"])

    def select_batch(self, ctx):
        if not self.is_enabled("pairs"):
            return None
        cams = sorted(ctx.train_cameras, key=lambda c: c.frame_index)
        k = int(torch.randint(len(cams) - 1, (1,), generator=self.generator))
        self.pairs.append((cams[k].frame_index, cams[k + 1].frame_index))
        return [cams[k], cams[k + 1]]

    def extra_features(self, ctx, view_index: int):
        feats: dict[str, Tensor] = {}
        if self.is_enabled("dynamic_channel"):
            feats["dynamic"] = ctx.model.gaussian_buffers["is_dynamic"]
        if self.is_enabled("pairs") and len(ctx.views) == 2:
            this, other = ctx.views[view_index], ctx.views[1 - view_index]
            if ctx.stage == "fine" and not self.deformation_checked:
                # The same Gaussians at the other view's time, evaluated on demand.
                again = ctx.model.deform(other.camera.time, ctx.stage)
                torch.testing.assert_close(again.means, other.state.means)
                self.deformation_checked = True
            feats["displacement"] = other.projection.means2d - this.projection.means2d
        return feats

    def extra_losses(self, ctx):
        if self.toy.toy_dynamic_weight == 0 or not self.is_enabled("dynamic_channel"):
            return None
        dyn = torch.stack([v.extras["dynamic"].mean() for v in ctx.views]).mean()
        return {"dynamic": self.toy.toy_dynamic_weight * dyn}

    def post_densify(self, ctx) -> None:
        self.calls["post_densify"] += 1
        self.buffer_sizes_ok &= ctx.model.gaussian_buffers["is_dynamic"].shape[0] == ctx.model.num_gaussians

    def on_iteration_end(self, ctx) -> None:
        self.calls["iterations"] += 1
        if ctx.stage == "fine" and self.is_enabled("warmup_freeze") and ctx.iteration == self.toy.toy_warmup_iterations:
            ctx.model.unfreeze(["deformation", "grid"])

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state(), "calls": dict(self.calls)}

    def load_state_dict(self, state) -> None:
        self.generator.set_state(state["generator"])
        self.calls = Counter(state["calls"])
