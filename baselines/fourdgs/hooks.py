"""The typed context handed to every hook, and the runner that calls the plugins' hooks.

Order of hook calls in one training run (see trainer.py):

    on_scene_loaded -> initial_point_cloud -> build_model -> on_model_created
      (or, starting from a point_cloud/iteration_N folder: on_scene_loaded -> build_model -> on_load)
    for stage in ("coarse", "fine"):
        on_stage_start
        every iteration:
            select_batch  select_partners  partner_rows  partner_shared_rows
            (host: deform + project every view of the batch, and every partner)
            extra_features(view k) for each view   (host: composite each view)
            loss_weights(view k) for each view  (host: baseline losses)  extra_losses
            pre_backward  (backward)  post_backward
            protected_gaussians  (host: densification) [post_densify]  (host: optimizer step)
            on_iteration_end
            [on_save when a point cloud is written]
        on_stage_end
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from .plugins import Plugin, PluginError

if TYPE_CHECKING:
    from arguments import TrainArgs
    from baselines.data import Camera, PointCloud, SceneInfo
    from baselines.render import Projection

    from .gaussian_model import GaussianModel
    from .state import GaussianState


@dataclass
class ViewRender:
    """Everything the host computed for one camera of the batch.

    Attributes:
        camera: the Camera (its image is the ground truth, [H, W, 3]).
        state: deformed Gaussians at camera.time (pre-activation, GaussianState).
        colors: [N, 3] view-dependent RGB from SH (None for a partner, which is never composited).
        projection: screen-space means/covariances/conics/depths/radii/visible ([N]-leading).
        image: [H, W, 3] render (with background); depth, alpha: [H, W, 1].
        extras: {name: [H, W, c]} maps of the plugins' extra feature channels.
    """

    camera: Camera
    state: GaussianState
    colors: Tensor | None
    projection: Projection
    image: Tensor | None = None
    depth: Tensor | None = None
    alpha: Tensor | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)


@dataclass
class TrainContext:
    """The one object every hook receives. Plugins read it and may set the fields they own.

    Attributes:
        args: all parameter groups (model, opt, pipe, hidden, extra plugin groups, run flags).
        scene: the loaded dataset. device: training device. model_path: output directory.
        train_cameras, test_cameras: the scene's cameras already moved to `device`.
        point_cloud / point_cloud_source: the initial cloud and where it came from.
        model: the GaussianModel (None before build). stage: "coarse" | "fine".
        iteration: 1-based iteration within the stage (4DGS numbering); stage_iterations: its total.
        batch: this iteration's cameras. views: their ViewRender, same order.
        partners: ViewRender of the cameras a plugin asked for with `select_partners`: deformed and
            projected only (never composited, not in the baseline loss or densification).
        losses: named, weighted loss terms; loss: their sum (set before pre_backward).
        metrics: scalars to log this iteration (plugins may add their own).
        densify_record: what densification did this iteration (or None).
        background: [3] background colour. state: free-form per-run storage for plugins, keyed by
            plugin name (e.g. ctx.state["reflow"]).
        hidden: [N] bool, the Gaussians a plugin hides on purpose in this stage (ReFlow's coarse
            stage hides the dynamic ones), or None; the stall guard does not wait for a render of a
            model whose every Gaussian is hidden.
    """

    args: TrainArgs
    scene: SceneInfo
    device: torch.device
    model_path: Path
    train_cameras: list[Camera] = field(default_factory=list)
    test_cameras: list[Camera] = field(default_factory=list)
    point_cloud: PointCloud | None = None
    point_cloud_source: str = ""
    model: GaussianModel | None = None
    stage: str = "coarse"
    iteration: int = 0
    stage_iterations: int = 0
    batch: list[Camera] = field(default_factory=list)
    views: list[ViewRender] = field(default_factory=list)
    partners: list[ViewRender] = field(default_factory=list)
    losses: dict[str, Tensor] = field(default_factory=dict)
    loss: Tensor | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    densify_record: Any = None
    background: Tensor | None = None
    state: dict[str, Any] = field(default_factory=dict)
    hidden: Tensor | None = None


class HookRunner:
    """Calls a hook on every plugin in order and combines the results."""

    def __init__(self, plugins: list[Plugin]) -> None:
        self.plugins = list(plugins)

    def call(self, hook: str, ctx: TrainContext, *args: Any) -> None:
        """Hooks without a result."""
        for plugin in self.plugins:
            getattr(plugin, hook)(ctx, *args)

    def first(self, hook: str, ctx: TrainContext, *args: Any) -> Any:
        """Replacement hooks: at most one plugin may return a value (None = not replacing)."""
        result, owner = None, None
        for plugin in self.plugins:
            value = getattr(plugin, hook)(ctx, *args)
            if value is not None:
                if owner is not None:
                    raise PluginError(f"plugins {owner!r} and {plugin.name!r} both replace {hook!r}; keep one")
                result, owner = value, plugin.name
        return result

    def merged(self, hook: str, ctx: TrainContext, *args: Any, prefix: bool = True) -> dict[str, Tensor]:
        """Dict-valued hooks: union of the plugins' dicts.

        With `prefix`, keys become "<plugin>/<key>" (loss names in logs); without, keys stay as
        the plugin wrote them (feature maps a plugin reads back) and a clash is an error.
        """
        merged: dict[str, Tensor] = {}
        for plugin in self.plugins:
            value = getattr(plugin, hook)(ctx, *args)
            for key, tensor in (value or {}).items():
                name = f"{plugin.name}/{key}" if prefix else key
                if name in merged:
                    raise PluginError(f"hook {hook!r}: two plugins return the key {name!r}")
                merged[name] = tensor
        return merged

    def combined_mask(self, hook: str, ctx: TrainContext, *args: Any) -> Tensor | None:
        """Bool-mask hooks: OR of the plugins' masks (None when no plugin returns one)."""
        result: Tensor | None = None
        for plugin in self.plugins:
            value = getattr(plugin, hook)(ctx, *args)
            if value is not None:
                result = value.bool() if result is None else result | value.bool()
        return result

    def product(self, hook: str, ctx: TrainContext, *args: Any) -> Tensor | None:
        """Weight hooks: product of the plugins' tensors (None when no plugin returns one)."""
        result: Tensor | None = None
        for plugin in self.plugins:
            value = getattr(plugin, hook)(ctx, *args)
            if value is not None:
                result = value if result is None else result * value
        return result

    def state_dict(self) -> dict[str, Any]:
        return {plugin.name: plugin.state_dict() for plugin in self.plugins}

    def load_state_dict(self, states: dict[str, Any]) -> None:
        for plugin in self.plugins:
            if plugin.name in states:
                plugin.load_state_dict(states[plugin.name])
