"""Separation-based dynamic scene modeling (paper 3.2.2, appendix A.2) as the plugin runs it: the
dynamic branch's learning rates and position scale, the keyframe seeds' temporal windows, and the
coarse stage that fits the static scene alone.

`SeparatedModeling` is a mixin of `ReFlowPlugin` (plugin.py): its methods read the plugin's `p`
(ReFlowParams), `info`, `seed_times`, `keyframe_times` and `is_enabled`. The deformation module
itself (static/dynamic split, relative and anchored time, window cull) is separation.py.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from baselines.fourdgs.gaussian_model import GaussianModel

from .params import TIME_SCALE_LR
from .seeding import window_scale
from .separation import TIME_CENTER, TIME_LOG_SCALE

HIDDEN_OPACITY = "reflow_hidden_opacity"  # buffer holding the dynamic opacities during the coarse stage
HIDDEN_LOGIT = -30.0


class SeparatedModeling:
    """Static/dynamic Gaussians: the dynamic branch's scale and windows, the static-first coarse stage."""

    def _dynamic(self, ctx) -> Tensor:
        return ctx.model.deformation_table

    def _scale_dynamic_branch(self, model: GaussianModel) -> None:
        """The dynamic branch's learning rates (`_dynamic_lr_multiplier`) and position scale.

        Above the extent cap the rates stop growing with the extent; the position deltas are
        multiplied by extent / cap instead (a reparametrisation, exact for the
        branch: its inputs are normalised to the dynamic box, its loss gradients scale as 1 / extent),
        so a scene at scale 50 trains its motion as the same scene at extent `cap` would, not 50x
        more slowly relative to its size (README, "Real priors": truck).
        """
        for group in ("deformation", "grid"):
            model.scale_learning_rate(group, self._dynamic_lr_multiplier(model))
        extent, cap = float(model.spatial_lr_scale), self.p.dynamic_lr_extent_cap
        scale = extent / cap if cap > 0 and extent > cap else 1.0
        net = getattr(model.deformation, "deformation_net", None)
        if net is not None and hasattr(net, "set_position_scale"):
            net.set_position_scale(scale)
            self.info["dynamic_position_scale"] = scale

    def _dynamic_lr_multiplier(self, model: GaussianModel) -> float:
        """`dynamic_lr_scale`, with 4DGS's scene-extent factor of these rates capped at `dynamic_lr_extent_cap`.

        4DGS multiplies the deformation and grid rates by the scene extent; on top of our 10x that
        diverges on large-scale scenes (COLMAP units), so above the cap the extent factor is undone.
        """
        extent, cap = float(model.spatial_lr_scale), self.p.dynamic_lr_extent_cap
        multiplier = self.p.dynamic_lr_scale * (min(1.0, cap / extent) if cap > 0 and extent > 0 else 1.0)
        self.info["dynamic_lr_multiplier"] = multiplier
        return multiplier

    def _register_windows(self, model: GaussianModel) -> None:
        """Temporal opacity windows of keyframe seeds (none with a single reference frame)."""
        times = getattr(self, "seed_times", None)
        if times is None or len(times) != model.num_gaussians or len(self.keyframe_times) < 2:
            return
        seeded = np.isfinite(times)
        centers = np.where(seeded, times, 0.5)
        log_scales = np.where(seeded, np.log(window_scale(self.keyframe_times)), np.log(1e3))
        model.register_gaussian_buffer(TIME_CENTER, torch.as_tensor(centers, dtype=torch.float32).unsqueeze(1))
        model.register_gaussian_parameter(TIME_LOG_SCALE, torch.as_tensor(log_scales, dtype=torch.float32).unsqueeze(1),
                                          TIME_SCALE_LR)

    def _hides_dynamic(self, ctx) -> bool:
        return HIDDEN_OPACITY in ctx.model.registered_buffers

    def _hide_dynamic_in_coarse(self, ctx) -> None:
        """Coarse stage: dynamic Gaussians are made invisible (their opacity kept in a buffer that
        follows densification), so the static scene is fitted alone; the fine stage restores them."""
        model = ctx.model
        if not self.is_enabled("separation"):
            return
        dynamic = model.deformation_table
        with torch.no_grad():
            if ctx.stage == "coarse" and bool(dynamic.any()) and HIDDEN_OPACITY not in model.registered_buffers:
                model.register_gaussian_buffer(HIDDEN_OPACITY, model._opacity.detach().clone())
                model._opacity[dynamic] = HIDDEN_LOGIT
                ctx.hidden = dynamic.clone()
            elif ctx.stage == "fine" and HIDDEN_OPACITY in model.registered_buffers:
                saved = model.pop_gaussian_buffer(HIDDEN_OPACITY)
                model._opacity[dynamic] = saved[dynamic]
                ctx.hidden = None
