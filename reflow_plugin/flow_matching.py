"""Self-correction flow matching (paper 3.3, appendix A.3) as the plugin runs it: which flow
directions an iteration computes (pair mode, flow_every, camera motion, the coarse stage) and the
FlowPairs that matching.py turns into losses; the external-flow comparison (component ext_flow).

    full, cam = plugin._flags(ctx)          # per direction of plugin._targets(ctx): which terms run
    pairs = plugin._flow_pairs(ctx, cam)    # matching.FlowPair per direction

`FlowMatching` is a mixin of `ReFlowPlugin` (plugin.py): its methods read the plugin's `p`
(ReFlowParams), `config` (MatchingConfig), `sampler`, `reference`, `keyframe_times`,
`mask_tensors`, `scene_depth`, `is_enabled` and the partner state set by `select_partners`
(`_partner_cameras`, `_partners_projected`), and keep the caches `_blur_cache`,
`_camera_motion`, `_any_dynamic` and `external`. The flow maps are flow.py, the losses matching.py.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from .external import ExternalFlowCache, external_flow_loss
from .flow import camera_motion_pixels, full_flow
from .matching import DYNAMIC_KEY, FLOW_KEY, FlowPair, dynamic_share
from .pairs import curriculum_radius
from .params import FLOW_MIN_ALPHA
from .warp import gaussian_blur


class FlowMatching:
    """Flow directions and pairs of an iteration, for matching.flow_losses."""

    @property
    def uses_pairs(self) -> bool:
        return self.is_enabled("full_flow") or self.is_enabled("cam_flow") or self.is_enabled("ext_flow")

    @property
    def renders_both(self) -> bool:
        """`pair_mode both`: the paper's pairwise batch (both frames rendered, both directions)."""
        return self.p.pair_mode == "both"

    def _flow_step(self, ctx) -> bool:
        """Whether this iteration computes flow terms (every `flow_every` iterations)."""
        return ctx.iteration % self.p.flow_every == 0

    def _full_now(self, ctx) -> bool:
        """Full flow channels are rendered this iteration (full flow matching or the external-flow L1)."""
        wanted = self.is_enabled("full_flow") or self.is_enabled("ext_flow")
        return wanted and ctx.stage == "fine" and self._flow_step(ctx) and self._has_dynamic(ctx)

    def _has_dynamic(self, ctx) -> bool:
        """Full flow only differs from camera flow where something moves: with separation and no
        dynamic Gaussian (a static scene) there are no full-flow terms; camera flow covers it."""
        if not (self.is_enabled("separation") and self.is_enabled("cam_flow")):
            return True
        table = self._dynamic(ctx)
        # asked several times per step; the model replaces (never edits) its table when labels change
        if self._any_dynamic is None or self._any_dynamic[0] is not table:
            self._any_dynamic = (table, bool(table.any()))
        return self._any_dynamic[1]

    def _cam_between(self, a, b) -> bool:
        """Camera flow a -> b is computed (the cameras move enough for it to say anything)."""
        key = (a.uid, b.uid)
        if key not in self._camera_motion:
            self._camera_motion[key] = camera_motion_pixels(b.K, a.viewmat, b.viewmat, self.scene_depth)
        return self._camera_motion[key] >= self.p.cam_flow_min_motion

    def _targets(self, ctx) -> list[tuple[int, Any, Any]]:
        """This iteration's flow directions: (source view index, target camera, target's prepared
        view or None when it was not projected)."""
        if self.renders_both:
            if len(ctx.views) != 2:
                return []
            return [(0, ctx.views[1].camera, ctx.views[1]), (1, ctx.views[0].camera, ctx.views[0])]
        projected = iter(ctx.partners)
        out = []
        for k, camera in enumerate(self._partner_cameras):
            if camera is not None:
                out.append((k, camera, next(projected, None) if self._partners_projected else None))
        return out

    def _flags(self, ctx) -> tuple[list[bool], list[bool]]:
        """Per direction of `_targets`: (full flow terms, camera flow terms) computed."""
        targets = self._targets(ctx)
        full = [self.is_enabled("full_flow") and self._full_now(ctx) and t[2] is not None for t in targets]
        cam = [self.is_enabled("cam_flow") and self._flow_step(ctx) and self._cam_between(ctx.views[k].camera, b)
               and (not self._coarse_hidden(ctx) or self._coarse_moving(ctx.views[k].camera, b) is not None)
               for k, b, _ in targets]
        return full, cam

    def _coarse_hidden(self, ctx) -> bool:
        """Coarse stage with the dynamic Gaussians hidden: the rendered dynamic-ness channel is 0
        everywhere, so it would call the moving object's pixels static."""
        return ctx.stage == "coarse" and self._hides_dynamic(ctx)

    def _coarse_moving(self, source, target) -> tuple[Tensor, Tensor] | None:
        """The motion masks (source's, target's) that keep the moving object out of coarse-stage
        camera flow; None when either frame has none (camera flow is then skipped for the pair)."""
        a, b = self.mask_tensors.get(source.uid), self.mask_tensors.get(target.uid)
        return None if a is None or b is None else (a.bool(), b.bool())

    @property
    def _uses_curriculum(self) -> bool:
        return (self.reference is not None and self.p.curriculum_fraction > 0
                and len(self.keyframe_times) == 1)

    def _curriculum_span(self, ctx) -> tuple[int, int]:
        """(reference position, allowed radius) of the curriculum at this iteration."""
        total = int(self.p.curriculum_fraction * ctx.stage_iterations)
        position = self.sampler.position[self.reference]
        span = max(position, self.sampler.num_frames - 1 - position)
        return position, curriculum_radius(ctx.iteration, total, span)

    def _blurred_image(self, camera, sigma: float) -> Tensor:
        key = (camera.image_name, sigma)
        if key not in self._blur_cache:
            self._blur_cache[key] = gaussian_blur(camera.image, sigma)
        return self._blur_cache[key]

    def _flow_pairs(self, ctx, cam: list[bool]) -> list[FlowPair]:
        """The directions of `_targets` as matching's FlowPair (target render / dynamic share when known)."""
        pairs = []
        targets = self._targets(ctx)
        for (k, camera, _), use_cam in zip(targets, cam):
            render, dynamic = None, None
            if self.renders_both:
                other = ctx.views[1 - k]
                render = other.image
                if use_cam and self.config.cam_target_static and DYNAMIC_KEY in other.extras:
                    dynamic = dynamic_share(other)
            elif use_cam and self.config.cam_target_static and camera.uid in self.mask_tensors:
                dynamic = self.mask_tensors[camera.uid].to(ctx.views[k].colors.dtype)
            reverse = 1 - k if self.renders_both else None
            moving = self._coarse_moving(ctx.views[k].camera, camera) if use_cam and self._coarse_hidden(ctx) else None
            pairs.append(FlowPair(ctx.views[k], camera, render, dynamic, reverse, moving))
        return pairs

    def _external_loss(self, pairs: list[FlowPair]) -> Tensor:
        """Every direction's L1 to the cached DIS flow (reflow_plugin.external)."""
        if self.external is None:
            self.external = ExternalFlowCache(self._run_dir_path / "external_flow")
        terms = []
        for pair in pairs:
            a = pair.source
            flow, valid = full_flow(a.extras[FLOW_KEY], a.alpha, FLOW_MIN_ALPHA)
            flow_ext, confident = self.external.get(a.camera, pair.target)
            terms.append(external_flow_loss(flow, valid, flow_ext, confident))
        return torch.stack(terms).mean()
