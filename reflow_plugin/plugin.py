"""`ReFlowPlugin`: ReFlow (CVPR 2026) wired into the 4DGS host through its hooks only.

    python train.py -s data/nvidia/Skating --plugin reflow [--disable full_flow,cam_flow]

Components (``--disable`` / ``--enable``, the paper's ablation switches):
    comp_init   complete canonical space (part 2, reflow_plugin.canonical): its fused static cloud plus
                the keyframe seeds of `separation` (depth aligned to that cloud); the paper's
                reference-frame dynamic cloud with --dynamic_keyframes 1 or without separation
    separation  static/dynamic separated deformation + dynamic points seeded in the motion masks
    full_flow   full flow matching (L_mc + L_cr on the pair's rendered full flows)
    cam_flow    camera flow matching on static pixels
    occlusion   (off by default) forward-backward occlusion masks for full flow matching
    cam_occlusion (off by default) the same test on the pair's two camera flows
    ext_flow    (off by default) L1 between the rendered full flow and cached DIS optical flow: the
                paper's "Ours (External Flow)" row is `--enable ext_flow --disable full_flow`

Hook by hook (order of hooks.py):
    on_scene_loaded      pair sampler (errors before long work: a single frame, no pairs)
    initial_point_cloud  canonical space (checked; canonical/check.py), or the host's cloud + labels by mask
                         vote + seeded dynamic points
    build_model          GaussianModel with SeparatedDeformation (separation)
    on_model_created     labels -> deformation table; dynamic HexPlane box fitted to dynamic points
    select_batch         a pair (a, b) of nearby training frames (widening from the reference frame)
    extra_features       per view: 7 full-flow channels towards the other view (fine stage), 1 dynamic-ness channel
    loss_weights         coarse stage: the baseline loss skips motion-mask pixels (static scene first)
    extra_losses         ff_mc, ff_cr, cf_mc, cf_cr (matching.py); ext (external.py, ext_flow)
    post_backward        coarse stage: dynamic Gaussians' gradients zeroed (frozen)
    protected_gaussians  dynamic Gaussians never pruned (protect_dynamic)
    on_iteration_end     warm-up unfreeze; flow-matching panels (flow_vis_every)
    on_load              a 4DGS folder (--start_checkpoint): labels from deformation magnitude (upgrade.py)
    on_stage_end         fine stage: flow metrics against ground truth when the dataset has it

Skips (only what the scene calls for): camera flow on pairs whose cameras barely move; the
dynamic branch when no Gaussian is dynamic (SeparatedDeformation); flow channels and pairs when
both flow losses are disabled (the host's own sampling then).
"""
from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from torch import Tensor

from baselines.data import PointCloud
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.plugins import Plugin

from .evaluate import flow_metrics, summary_line, write_flow_metrics
from .external import ExternalFlowCache, external_flow_loss
from .flow import camera_motion_pixels, flow_features, full_flow
from .labels import aligned_depths, training_masks, vote_labels
from .matching import DYNAMIC_KEY, FLOW_KEY, MatchingConfig, pair_losses
from .pairs import PairSampler, curriculum_radius
from .params import ReFlowParams
from .seeding import BACKGROUND_FACTOR, keyframes, reference_frame, ring_depth, seed_dynamic_points, window_scale
from .separation import TIME_CENTER, TIME_LOG_SCALE, SeparatedDeformation
from .upgrade import upgrade_4dgs_model, written_by_reflow
from .visualize import write_panel
from .warp import gaussian_blur

log = logging.getLogger("reflow")
RUN_FOLDER = "reflow"
HIDDEN_OPACITY = "reflow_hidden_opacity"  # buffer holding the dynamic opacities during the coarse stage
HIDDEN_LOGIT = -30.0


def canonical_available() -> tuple[bool, str]:
    """(whether reflow_plugin.canonical can be imported, why not)."""
    try:
        from . import canonical  # noqa: F401
    except ImportError as exc:
        return False, f"reflow_plugin.canonical is not installed ({exc})"
    return True, ""


class ReFlowPlugin(Plugin):
    name = "reflow"
    components = ("comp_init", "separation", "full_flow", "cam_flow", "occlusion", "cam_occlusion", "ext_flow")
    default_disabled = ("occlusion", "cam_occlusion", "ext_flow")
    param_groups = {"ReFlowParams": ReFlowParams}
    outputs = (RUN_FOLDER, "flow", "flow_metrics.json")  # what --overwrite clears of a ReFlow run

    def __init__(self, params: Mapping[str, Any] | None = None, enabled: frozenset[str] | None = None) -> None:
        super().__init__(params, enabled)
        self.p: ReFlowParams = self.params.get("ReFlowParams") or ReFlowParams()
        self.sampler: PairSampler | None = None
        self.masks: list[np.ndarray] | None = None  # per training camera (uid order), True = dynamic
        self.mask_tensors: dict[int, Tensor] = {}
        self.labels: np.ndarray | None = None  # per initial point, True = dynamic
        self.reference: int | None = None  # training camera the dynamic points come from
        self.keyframe_times: list[float] = []
        self.seed_times: np.ndarray | None = None  # per initial point: keyframe time, NaN if not seeded
        self.scene_depth = 1.0
        self.info: dict[str, Any] = {}
        self.config = MatchingConfig(
            lambda_ff=self.p.lambda_ff, lambda_cf=self.p.lambda_cf, lambda_mc=self.p.lambda_mc,
            cross_time_ratio=self.p.cross_time_ratio, ssim_weight=self.p.photo_ssim_weight,
            min_alpha=self.p.flow_min_alpha, blur_sigmas=tuple(self.p.flow_blur_sigmas),
            occlusion=self.is_enabled("occlusion"), occlusion_alpha1=self.p.occlusion_alpha1,
            occlusion_alpha2=self.p.occlusion_alpha2, cam_occlusion=self.is_enabled("cam_occlusion"),
            full_flow_dynamic_only=self.p.full_flow_region == "dynamic")
        self._blur_cache: dict[tuple[str, float], Tensor] = {}
        self._camera_motion: dict[tuple[int, int], float] = {}
        self._last = None
        self.external: ExternalFlowCache | None = None

    # ------------------------------------------------------------------ helpers
    @property
    def uses_pairs(self) -> bool:
        return self.is_enabled("full_flow") or self.is_enabled("cam_flow") or self.is_enabled("ext_flow")

    def _flow_step(self, ctx) -> bool:
        """Whether this iteration computes flow terms (every `flow_every` iterations)."""
        return ctx.iteration % self.p.flow_every == 0

    def _use_full(self, ctx) -> bool:
        return self.is_enabled("full_flow") and ctx.stage == "fine" and len(ctx.views) == 2 and self._flow_step(ctx)

    def _use_ext(self, ctx) -> bool:
        return self.is_enabled("ext_flow") and ctx.stage == "fine" and len(ctx.views) == 2 and self._flow_step(ctx)

    def _use_cam(self, ctx) -> bool:
        if not self.is_enabled("cam_flow") or len(ctx.batch) != 2 or not self._flow_step(ctx):
            return False
        if ctx.stage == "coarse" and self._hides_dynamic(ctx) and not self.mask_tensors:
            return False  # every pixel would count as static, the moving object's too: no camera flow yet
        a, b = ctx.batch
        key = (a.uid, b.uid)
        if key not in self._camera_motion:
            self._camera_motion[key] = camera_motion_pixels(b.K, a.viewmat, b.viewmat, self.scene_depth)
        return self._camera_motion[key] >= self.p.cam_flow_min_motion

    def _dynamic(self, ctx) -> Tensor:
        return ctx.model.deformation_table

    def _run_dir(self, ctx) -> Path:
        return Path(ctx.model_path) / RUN_FOLDER

    def min_train_frames(self) -> tuple[int, str]:
        """Pairs (full_flow, cam_flow, ext_flow) and the canonical alignment (comp_init) need 2 frames."""
        needs = [c for c in ("full_flow", "cam_flow", "ext_flow", "comp_init") if self.is_enabled(c)]
        return (2, ", ".join(needs)) if needs else (1, "")

    # ------------------------------------------------------------------ set-up
    def on_scene_loaded(self, ctx) -> None:
        if self.uses_pairs:
            self.sampler = PairSampler(ctx.train_cameras, self.p.pair_window, seed=ctx.args.opt.seed)
        available, reason = canonical_available()
        self.info["components"] = sorted(self.enabled)
        if self.is_enabled("comp_init") and not available:
            self.info["comp_init"] = f"unavailable: {reason}"
            log.warning("comp_init is enabled but %s; the host's initial cloud is used instead", reason)

    def initial_point_cloud(self, ctx) -> PointCloud | None:
        cameras = ctx.train_cameras
        host = ctx.point_cloud
        masks, source = training_masks(cameras, self.p.label_source, self._run_dir(ctx),
                                       aligned_depths(cameras, host.points))
        self.masks, self.info["mask_source"] = masks, source
        if masks is not None:
            self.mask_tensors = {c.uid: torch.from_numpy(m).to(ctx.device) for c, m in zip(cameras, masks)}
        if self.is_enabled("comp_init") and canonical_available()[0]:
            cloud = self._canonical_cloud(ctx, masks)
            if cloud is not None:
                return cloud
        return self._host_cloud(ctx, masks, source)

    def _host_cloud(self, ctx, masks, source) -> PointCloud | None:
        """Part 1: the host's cloud, labelled by mask vote, plus keyframe seeds (None: the host's as is)."""
        cameras, host = ctx.train_cameras, ctx.point_cloud
        depths = aligned_depths(cameras, host.points, masks)
        labels = (vote_labels(host.points, cameras, masks, depths, self.p.label_vote) if masks is not None
                  else np.zeros(len(host), bool))
        cloud = host
        self.info["initial_cloud"] = ctx.point_cloud_source
        self.seed_times = np.full(len(host), np.nan)
        if masks is not None and self.is_enabled("separation") and self.p.seed_points > 0:
            self.reference = reference_frame(cameras, masks)
            if self.reference is not None:
                seeds, times = self._seed_keyframes(ctx, cameras, masks, depths, host)
                if len(seeds):
                    cloud = PointCloud(np.concatenate([host.points, seeds.points]),
                                       np.concatenate([host.colors, seeds.colors]))
                    labels = np.concatenate([labels, np.ones(len(seeds), bool)])
                    self.seed_times = np.concatenate([self.seed_times, times])
                    self.info["initial_cloud"] = f"{ctx.point_cloud_source} + {len(seeds)} seeded dynamic points"
        self.labels = labels
        log.info("initial cloud: %s; %d of %d points dynamic (masks: %s)", self.info["initial_cloud"],
                 int(labels.sum()), len(labels), source)
        return cloud if cloud is not host else None

    def _seed_keyframes(self, ctx, cameras, masks, depths, host) -> tuple[PointCloud, np.ndarray]:
        """Dynamic points from the keyframes' masks, and the time each was seeded at."""
        frames = keyframes(cameras, masks, self.p.dynamic_keyframes, self.reference)
        budget = max(1, self.p.seed_points // len(frames))
        clouds, times, used = [], [], []
        for k in frames:
            if depths is not None:
                depth, how = depths[k], "aligned disparity"
            else:
                ring = ring_depth(cameras[k], masks[k], host.points)
                if ring is None:
                    log.warning("no depth for the dynamic seeds of %s (no disparity, no static points nearby)",
                                cameras[k].image_name)
                    continue
                depth, how = BACKGROUND_FACTOR * ring, f"{BACKGROUND_FACTOR} x the surrounding static depth"
            seeds = seed_dynamic_points(cameras[k], masks[k], depth, budget, seed=ctx.args.opt.seed + k)
            clouds.append(seeds)
            times.append(np.full(len(seeds), cameras[k].time))
            used.append(cameras[k].image_name)
        self.keyframe_times = [cameras[k].time for k in frames]
        self.info["seed"] = {"reference": cameras[self.reference].image_name, "keyframes": used,
                             "depth": how if clouds else None}
        if not clouds:
            return PointCloud(np.zeros((0, 3)), np.zeros((0, 3))), np.zeros(0)
        return (PointCloud(np.concatenate([c.points for c in clouds]), np.concatenate([c.colors for c in clouds])),
                np.concatenate(times))

    def _canonical_cloud(self, ctx, masks) -> PointCloud | None:
        """Canonical STATIC cloud + part 1's keyframe seeds (their depth aligned to the static points)
        by default; the paper's reference-frame dynamic cloud with --dynamic_keyframes 1 or without
        separation (measured on the skating scene: the single reference cloud alone misses the skater).

        The cloud is checked before training (canonical/check.py: views, depth against the host's
        sparse points or the bounds, dynamic spread). A failing check logs one warning and falls
        back: the per-frame fits of the dataset's disparity to the sparse points, else to the
        bounds (no joint refinement, no raw pointmaps), else None (the caller uses the host's cloud
        + part 1's seeds). Recorded in info["canonical_check"].
        """
        from .canonical import build_canonical_space, options_from_params
        from .canonical.check import check_initial_cloud

        options = options_from_params(self.p)
        options.device = str(ctx.device)
        anchors = ctx.point_cloud.points if ctx.point_cloud_source in ("dataset", "triangulated") else None
        attempts = [("canonical space", options)]
        cameras = ctx.train_cameras
        keep = not self.p.canonical_check
        disparity = options.provider in ("auto", "depth") and all(c.disparity is not None for c in cameras)
        bounds = all(c.extras.get("near_far") is not None for c in cameras)
        if not keep and disparity and (anchors is not None or bounds) and (not options.align or options.refine):
            attempts.append((f"per-frame fits to the {'sparse points' if anchors is not None else 'bounds'}",
                             replace(options, align=True, refine=False)))
        failures = []
        for what, opts in attempts:
            space = build_canonical_space(ctx.scene, masks, opts, cache_dir=self._run_dir(ctx) / "canonical",
                                          progress=not ctx.args.run.quiet, anchors=anchors)
            static, dynamic, times, groups, described = self._compose(ctx, space, masks)
            check = check_initial_cloud(static.points, groups, ctx.train_cameras, anchors)
            if check.passed or keep:
                break
            failures.append(f"{what}: {check.failure}")
        else:
            space = None
        if not check.passed and keep:
            log.warning("initial cloud check failed (%s); kept (--no-canonical_check)", check.failure)
        self.info["canonical_check"] = dict(check.as_dict(), failures=failures,
                                            used=what if space is not None else "host cloud + part 1 seeds")
        if failures:
            log.warning("initial cloud check failed (%s); using the %s instead", "; ".join(failures),
                        self.info["canonical_check"]["used"])
        if space is None:
            return None
        space.write_ply(self._run_dir(ctx))
        self.info["canonical"] = space.report
        self.labels = np.concatenate([np.zeros(len(static), bool), np.ones(len(dynamic), bool)])
        self.seed_times = np.concatenate([np.full(len(static), np.nan), times])
        self.info["initial_cloud"] = f"{what}: {len(static)} static + {described}"
        log.info("initial cloud: %s", self.info["initial_cloud"])
        return PointCloud(np.concatenate([static.points, dynamic.points]),
                          np.concatenate([static.colors, dynamic.colors]))

    def _compose(self, ctx, space, masks):
        """(static cloud, dynamic cloud, seed times, DynamicGroups for the check, description)."""
        from .canonical.check import DynamicGroup

        static, cameras = space.static, ctx.train_cameras
        if len(static) == 0:  # every pixel masked or unconfident: the host's cloud stands in
            log.warning("canonical space: no static point; the host's %s cloud is used as the static cloud",
                        ctx.point_cloud_source)
            static = ctx.point_cloud
        self.reference = space.reference_frame
        keyframe_seeds = (masks is not None and self.reference is not None and self.is_enabled("separation")
                          and self.p.seed_points > 0 and self.p.dynamic_keyframes > 1)
        if keyframe_seeds:
            depths = aligned_depths(cameras, static.points, masks)
            dynamic, times = self._seed_keyframes(ctx, cameras, masks, depths, static)
            groups = [DynamicGroup(cameras[k], masks[k], dynamic.points[times == cameras[k].time])
                      for k in sorted({k for k, c in enumerate(cameras) if c.image_name in self.info["seed"]["keyframes"]})]
            return static, dynamic, times, groups, f"{len(dynamic)} keyframe-seeded dynamic points"
        dynamic, times = space.dynamic, np.full(len(space.dynamic), np.nan)
        groups = ([DynamicGroup(cameras[self.reference], masks[self.reference], dynamic.points)]
                  if self.reference is not None and masks is not None else [])
        return static, dynamic, times, groups, f"{len(dynamic)} dynamic points (reference frame)"

    def build_model(self, ctx) -> GaussianModel | None:
        if not self.is_enabled("separation"):
            return None
        deformation = SeparatedDeformation(ctx.args.hidden, self.p.static_decoder, self.p.dynamic_zero_init,
                                           self.p.relative_time, self.p.anchor_keyframes)
        return GaussianModel(ctx.args.model.sh_degree, ctx.args.hidden, deformation=deformation)

    def on_model_created(self, ctx) -> None:
        model = ctx.model
        labels = self.labels if self.labels is not None and len(self.labels) == model.num_gaussians else None
        table = torch.zeros(model.num_gaussians, dtype=torch.bool) if labels is None else torch.from_numpy(labels)
        model.set_deformation_table(table)
        dynamic = int(table.sum())
        self.info["labels"] = {"dynamic": dynamic, "static": model.num_gaussians - dynamic}
        if dynamic and self.is_enabled("separation"):
            with torch.no_grad():
                value = torch.logit(torch.tensor(self.p.dynamic_init_opacity).clamp(1e-4, 1 - 1e-4))
                model._opacity[model.deformation_table] = value
            self._register_windows(model)
        if self.is_enabled("separation"):
            for group in ("deformation", "grid"):
                model.scale_learning_rate(group, self._dynamic_lr_multiplier(model))
            if dynamic:
                model.deformation.fit_box(model.get_xyz.detach()[model.deformation_table], self.p.dynamic_aabb_margin)
            else:
                log.warning("separation: no Gaussian is labelled dynamic, so the scene is modelled as static "
                            "(label_source=%s; motion masks: %s)", self.p.label_source, self.info.get("mask_source"))
        self._record(ctx)

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
                                          self.p.time_scale_lr)

    @property
    def _uses_curriculum(self) -> bool:
        return (self.reference is not None and self.p.curriculum_fraction > 0
                and len(self.keyframe_times) == 1)

    def on_load(self, ctx, point_cloud_dir) -> None:
        source = self.p.upgrade_labels
        if source == "motion" or (source == "auto" and not written_by_reflow(point_cloud_dir)):
            times = sorted({float(c.time) for c in ctx.train_cameras})
            self.info["upgrade"] = upgrade_4dgs_model(ctx.model, times, self.p.upgrade_motion_threshold,
                                                      ctx.scene.cameras_extent, bake=self.is_enabled("separation"))
            log.info("upgraded %s: %d dynamic, %d static Gaussians (motion > %.4g world units)", point_cloud_dir,
                     self.info["upgrade"]["dynamic"], self.info["upgrade"]["static"],
                     self.info["upgrade"]["threshold_world"])
        if self.is_enabled("separation"):
            for group in ("deformation", "grid"):
                ctx.model.scale_learning_rate(group, self._dynamic_lr_multiplier(ctx.model))
        table = ctx.model.deformation_table
        self.info["labels"] = {"dynamic": int(table.sum()), "static": int((~table).sum())}

    def on_stage_start(self, ctx) -> None:
        means = ctx.model.get_xyz.detach()
        cam = ctx.train_cameras[0]
        z = means @ cam.viewmat[:3, :3].T[:, 2] + cam.viewmat[2, 3]
        z = z[z > 0]
        self.scene_depth = float(z.median()) if z.numel() else 1.0
        if ctx.stage == "fine" and self.p.dynamic_warmup > 0 and self.is_enabled("separation"):
            ctx.model.freeze(["deformation", "grid"])
        self._hide_dynamic_in_coarse(ctx)

    def _hides_dynamic(self, ctx) -> bool:
        return HIDDEN_OPACITY in ctx.model.registered_buffers

    def _hide_dynamic_in_coarse(self, ctx) -> None:
        """Coarse stage: dynamic Gaussians are made invisible (their opacity kept in a buffer that
        follows densification), so the static scene is fitted alone; the fine stage restores them."""
        model = ctx.model
        if not self.is_enabled("separation") or not self.p.coarse_static_only:
            return
        dynamic = model.deformation_table
        with torch.no_grad():
            if ctx.stage == "coarse" and bool(dynamic.any()) and HIDDEN_OPACITY not in model.registered_buffers:
                model.register_gaussian_buffer(HIDDEN_OPACITY, model._opacity.detach().clone())
                model._opacity[dynamic] = HIDDEN_LOGIT
            elif ctx.stage == "fine" and HIDDEN_OPACITY in model.registered_buffers:
                saved = model.pop_gaussian_buffer(HIDDEN_OPACITY)
                model._opacity[dynamic] = saved[dynamic]

    # ------------------------------------------------------------------ per iteration
    def select_batch(self, ctx) -> list | None:
        if self.sampler is None:
            return None
        if ctx.stage == "fine" and self._uses_curriculum:
            total = int(self.p.curriculum_fraction * ctx.stage_iterations)
            position = self.sampler.position[self.reference]
            span = max(position, self.sampler.num_frames - 1 - position)
            i, j = self.sampler.sample(position, curriculum_radius(ctx.iteration, total, span))
        else:
            i, j = self.sampler.sample()
        return [ctx.train_cameras[i], ctx.train_cameras[j]]

    def extra_features(self, ctx, view_index: int) -> dict[str, Tensor] | None:
        if len(ctx.views) != 2:
            return None
        features: dict[str, Tensor] = {}
        if self._use_full(ctx) or self._use_ext(ctx):
            features[FLOW_KEY] = flow_features(ctx.views[view_index].projection, ctx.views[1 - view_index].projection)
        if self._use_cam(ctx) or (self._use_full(ctx) and self.config.full_flow_dynamic_only):
            features[DYNAMIC_KEY] = self._dynamic(ctx).to(ctx.views[view_index].colors.dtype).unsqueeze(1)
        return features

    def loss_weights(self, ctx, view_index: int) -> Tensor | None:
        if ctx.stage != "coarse" or not self.p.coarse_static_only or not self.mask_tensors:
            return None
        mask = self.mask_tensors.get(ctx.views[view_index].camera.uid)
        return None if mask is None else (~mask).float().unsqueeze(-1)

    def _coarse_moving(self, ctx) -> list[Tensor] | None:
        """Coarse stage: the pair's motion masks. Nothing is deformed yet (and the dynamic Gaussians are
        hidden, so the rendered dynamic-ness calls every pixel static): the masks keep the moving
        object out of camera-flow matching."""
        if ctx.stage != "coarse" or not self.mask_tensors:
            return None
        masks = [self.mask_tensors.get(view.camera.uid) for view in ctx.views]
        return None if any(m is None for m in masks) else [m.bool() for m in masks]

    def _blurred(self, ctx, k: int, sigma: float) -> tuple[Tensor, Tensor]:
        images = []
        for view in (ctx.views[1 - k], ctx.views[k]):
            key = (view.camera.image_name, sigma)
            if key not in self._blur_cache:
                self._blur_cache[key] = gaussian_blur(view.camera.image, sigma)
            images.append(self._blur_cache[key])
        return images[0], images[1]

    def extra_losses(self, ctx) -> dict[str, Tensor] | None:
        use_full, use_cam, use_ext = self._use_full(ctx), self._use_cam(ctx), self._use_ext(ctx)
        if len(ctx.views) != 2 or not (use_full or use_cam or use_ext):
            self._last = None
            return None
        result = pair_losses(ctx.views, self.config, use_full, use_cam,
                             lambda k, sigma: self._blurred(ctx, k, sigma), moving=self._coarse_moving(ctx))
        if use_ext:
            result.losses["ext"] = self.p.lambda_ext * self._external_loss(ctx)
        ctx.metrics.update(result.metrics)
        dynamic = self._dynamic(ctx)
        if bool(dynamic.any()):
            ctx.metrics["dynamic_opacity"] = float(torch.sigmoid(ctx.model._opacity.detach()[dynamic]).mean())
        self._last = result
        return result.losses

    def _external_loss(self, ctx) -> Tensor:
        """Both directions' L1 to the cached DIS flow (reflow_plugin.external)."""
        if self.external is None:
            self.external = ExternalFlowCache(self._run_dir(ctx) / "external_flow")
        terms = []
        for k in range(2):
            a, b = ctx.views[k], ctx.views[1 - k]
            flow, valid = full_flow(a.extras[FLOW_KEY], a.alpha, self.p.flow_min_alpha)
            flow_ext, confident = self.external.get(a.camera, b.camera)
            terms.append(external_flow_loss(flow, valid, flow_ext, confident))
        return torch.stack(terms).mean()

    def post_backward(self, ctx) -> None:
        if not self.is_enabled("separation"):
            return
        settling = ctx.stage == "fine" and ctx.iteration <= self.p.dynamic_settle_fraction * ctx.stage_iterations
        frozen = (ctx.stage == "coarse" and self.p.coarse_static_only) or settling
        dynamic = self._dynamic(ctx)
        if frozen and bool(dynamic.any()):
            ctx.model.zero_row_gradients(dynamic)

    def protected_gaussians(self, ctx) -> Tensor | None:
        if self.p.protect_dynamic and self.is_enabled("separation"):
            return self._dynamic(ctx)
        return None

    def on_iteration_end(self, ctx) -> None:
        if ctx.stage != "fine":
            return
        if self.p.dynamic_warmup > 0 and ctx.iteration == self.p.dynamic_warmup and self.is_enabled("separation"):
            ctx.model.unfreeze(["deformation", "grid"])
        every = self.p.flow_vis_every
        if every and self._last is not None and (ctx.iteration % every == 0 or ctx.iteration == ctx.stage_iterations):
            direction = self._last.directions[0]
            if direction.flow is not None:
                a, b = ctx.views
                write_panel(self._run_dir(ctx) / "flow_vis" / f"{ctx.iteration:06d}_{a.camera.image_name}_{b.camera.image_name}.png",
                            a.camera.image.cpu().numpy(), direction.warped.detach().cpu().numpy(),
                            b.camera.image.cpu().numpy(), direction.valid.cpu().numpy(),
                            direction.flow.detach().cpu().numpy())

    def on_stage_end(self, ctx) -> None:
        if ctx.stage != "fine":
            return
        method = f"ours_{ctx.iteration}"
        metrics = flow_metrics(ctx.model, ctx.train_cameras, ctx.test_cameras, Path(ctx.scene.source_path),
                               ctx.args.pipe.backend, self._run_dir(ctx).parent / "flow" / method, images=4)
        write_flow_metrics(ctx.model_path, method, metrics)
        log.info(summary_line(metrics))
        self._record(ctx)

    def _record(self, ctx) -> None:
        """The plugin's facts (components, initial cloud, labels) into results.json["reflow"]."""
        path = Path(ctx.model_path) / "results.json"
        data = json.loads(path.read_text()) if path.is_file() else {}
        data["reflow"] = self.info
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True, default=str))
        tmp.replace(path)

    def viewer_modes(self) -> dict[str, Any]:
        """The web viewer's "full flow" mode (reflow_plugin/viewer_modes.py)."""
        from .viewer_modes import VIEWER_MODES

        return dict(VIEWER_MODES)

    # ------------------------------------------------------------------ persistence
    def state_dict(self) -> dict[str, Any]:
        return {"sampler": self.sampler.state_dict() if self.sampler is not None else None,
                "reference": self.reference, "keyframe_times": list(self.keyframe_times)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if state.get("sampler") is not None and self.sampler is not None:
            self.sampler.load_state_dict(state["sampler"])
        self.reference = state.get("reference")
        self.keyframe_times = list(state.get("keyframe_times", []))
