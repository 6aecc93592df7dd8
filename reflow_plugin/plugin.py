"""`ReFlowPlugin`: ReFlow (CVPR 2026) wired into the 4DGS host through its hooks only.

    python train.py -s data/nvidia/Skating --plugin reflow [--disable full_flow,cam_flow]

Components (``--disable`` / ``--enable``, the paper's ablation switches):
    comp_init   complete canonical space (part 2, reflow_plugin.canonical): its fused static cloud plus
                the keyframe seeds of `separation` (depth aligned to that cloud); the paper's
                reference-frame dynamic cloud with --dynamic_keyframes 1 or without separation
    separation  static/dynamic separated deformation + dynamic points seeded in the motion masks
    full_flow   full flow matching (L_mc + L_cr on the pair's rendered full flows)
    cam_flow    camera flow matching on static pixels
    occlusion   (off by default) forward-backward occlusion masks for full flow matching (pair_mode both)
    cam_occlusion (off by default) the same test on the pair's two camera flows (pair_mode both)
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

from .disparity_field import correct_disparity
from .evaluate import flow_metrics, summary_line, write_flow_metrics
from .external import ExternalFlowCache, external_flow_loss
from .flow import camera_motion_pixels, flow_features, full_flow
from .labels import aligned_depths, training_masks, vote_labels
from .matching import DYNAMIC_KEY, FLOW_KEY, FlowPair, MatchingConfig, check_occlusion_mode, dynamic_share, flow_losses
from .pairs import PairSampler, curriculum_radius
from .params import ReFlowParams
from .promotion import ResidualVotes, missed_motion_maps, promoted_gaussians
from .seeding import BACKGROUND_FACTOR, keyframes, reference_frame, ring_depth, seed_dynamic_points, window_scale
from .separation import TIME_CENTER, TIME_LOG_SCALE, SeparatedDeformation
from .upgrade import upgrade_4dgs_model, written_by_reflow
from .visualize import write_panel
from .warp import gaussian_blur

log = logging.getLogger("reflow")
RUN_FOLDER = "reflow"
HIDDEN_OPACITY = "reflow_hidden_opacity"  # buffer holding the dynamic opacities during the coarse stage
HIDDEN_LOGIT = -30.0
METRIC_SOURCES = ("dataset", "triangulated")  # host clouds whose points are metric evidence (not "random")


def _metric_points(ctx) -> np.ndarray:
    """[P, 3] the host's points where they measure the scene (dataset / triangulated), else [0, 3]:
    a random cloud must not be fitted as if it were (the disparity then takes the bounds' fit)."""
    if ctx.point_cloud_source in METRIC_SOURCES:
        return np.asarray(ctx.point_cloud.points, np.float64)
    return np.zeros((0, 3))


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
        self.coarse_fitted = False  # a coarse stage ran in this process (promotion reads its fit)
        self.depth_cameras: list = []  # the training cameras as the depth steps read them (initial_point_cloud)
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
            # without separation there is no static/dynamic model to split the pixels by: all pixels
            full_flow_dynamic_only=self.p.full_flow_region == "dynamic" and self.is_enabled("separation"),
            full_flow_min_share=self.p.full_flow_min_share,
            cam_target_static=self.p.cam_flow_target_static, blur_dynamic_only=self.p.flow_blur_region == "dynamic")
        self._blur_cache: dict[tuple[str, float], Tensor] = {}
        self._camera_motion: dict[tuple[int, int], float] = {}
        self._any_dynamic: tuple[Tensor, bool] | None = None  # (labels tensor, any dynamic): _has_dynamic
        self._partner_cameras: list = []  # pair_mode partner: per batch view, its frame b (or None)
        self._partners_projected = False
        self._run_dir_path = Path(".")
        self._last = None
        self.external: ExternalFlowCache | None = None
        self.relabel = ResidualVotes(self.p.relabel_residual) if self.p.relabel_every > 0 else None

    # ------------------------------------------------------------------ helpers
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
        self._run_dir_path = self._run_dir(ctx)
        if self.uses_pairs:
            self.sampler = PairSampler(ctx.train_cameras, self.p.pair_window, seed=ctx.args.opt.seed)
        available, reason = canonical_available()
        self.info["components"] = sorted(self.enabled)
        if self.is_enabled("comp_init") and not available:
            self.info["comp_init"] = f"unavailable: {reason}"
            log.warning("comp_init is enabled but %s; the host's initial cloud is used instead", reason)

    def initial_point_cloud(self, ctx) -> PointCloud | None:
        # a training run only (render.py must still load a run recorded with the switch on)
        check_occlusion_mode(self.config.occlusion, self.config.cam_occlusion, self.p.pair_mode)
        cameras = self.depth_cameras = self._corrected_disparity(ctx)
        masks, source = training_masks(cameras, self.p.label_source, self._run_dir(ctx),
                                       aligned_depths(cameras, _metric_points(ctx)), self.p.mask_offsets,
                                       self.slow_mask_offsets())
        self.masks, self.info["mask_source"] = masks, source
        if masks is not None:
            self.mask_tensors = {c.uid: torch.from_numpy(m).to(ctx.device) for c, m in zip(cameras, masks)}
        if self.is_enabled("comp_init") and canonical_available()[0]:
            cloud = self._canonical_cloud(ctx, masks)
            if cloud is not None:
                return cloud
        return self._host_cloud(ctx, masks, source)

    def slow_mask_offsets(self) -> tuple[int, ...]:
        """The estimated masks' slow-motion pairing (`--mask_slow_offsets`; 0 alone = off: empty)."""
        return tuple(int(o) for o in self.p.mask_slow_offsets if o != 0)

    def _corrected_disparity(self, ctx) -> list:
        """The training cameras, their disparity with the smooth per-frame correction (disparity_field.py)
        where it was kept; the cameras themselves without disparity, sparse points or `disparity_field`.
        Fitted to the sparse points outside the dataset's motion masks; without them (estimated masks
        come later, from this depth) to every sparse point, the field's biweight the only guard."""
        cameras = ctx.train_cameras
        points = _metric_points(ctx)
        if (self.p.disparity_field == 0 or len(points) == 0
                or any(c.disparity is None for c in cameras)):
            return list(cameras)
        out, reports = [], []
        for cam in cameras:
            disparity = cam.disparity.detach().cpu().numpy().astype(np.float64)
            static = None if cam.mask is None else cam.mask.detach().cpu().numpy() > 0.5  # the dataset's masks
            corrected, report = correct_disparity(cam, disparity, points, self.p.disparity_field, static)
            reports.append(report)
            out.append(replace(cam, disparity=torch.as_tensor(corrected, dtype=cam.disparity.dtype,
                                                              device=cam.disparity.device))
                       if report["corrected"] else cam)
        done = [r for r in reports if r["corrected"]]
        before = float(np.median([r["residual"] for r in done])) if done else None
        after = float(np.median([r["residual_corrected"] for r in done])) if done else None
        self.info["disparity_field"] = {"grid": self.p.disparity_field, "frames": len(cameras),
                                        "corrected": len(done), "residual": before, "residual_corrected": after,
                                        "held_out": {c.image_name: r["held_out_after"]  # what the check gates on
                                                     for c, r in zip(cameras, reports) if r["corrected"]}}
        if done:
            log.info("disparity: a smooth correction kept in %d of %d frames (median residual at the sparse "
                     "points %.3f -> %.3f)", len(done), len(cameras), before, after)
        return out

    def _host_cloud(self, ctx, masks, source) -> PointCloud | None:
        """Part 1: the host's cloud, labelled by mask vote, plus keyframe seeds (None: the host's as is)."""
        cameras, host = self.depth_cameras, ctx.point_cloud
        depths = aligned_depths(cameras, _metric_points(ctx), masks)
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
            seeds = seed_dynamic_points(cameras[k], masks[k], depth, budget, seed=ctx.args.opt.seed + k,
                                        edge_ratio=self.p.seed_edge_ratio)
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
        + part 1's seeds). A depth prior whose fits to the sparse points leave more than
        --canonical_max_fit_residual, or a cloud whose depth disagrees with them by more than
        --canonical_max_depth_error, goes straight to the host's cloud (the per-frame fits use the
        same prior). Recorded in info["canonical_check"].
        """
        from .canonical import build_canonical_space, options_from_params
        from .canonical.check import check_initial_cloud, prior_residual

        options = options_from_params(self.p)
        options.device = str(ctx.device)
        anchors = _metric_points(ctx) if ctx.point_cloud_source in METRIC_SOURCES else None
        attempts = [("canonical space", options)]
        cameras = self.depth_cameras
        keep = not self.p.canonical_check
        disparity = options.provider in ("auto", "depth") and all(c.disparity is not None for c in cameras)
        bounds = all(c.extras.get("near_far") is not None for c in cameras)
        if not keep and disparity and (anchors is not None or bounds) and (not options.align or options.refine):
            attempts.append((f"per-frame fits to the {'sparse points' if anchors is not None else 'bounds'}",
                             replace(options, align=True, refine=False)))
        failures = []
        for what, opts in attempts:
            space = build_canonical_space(replace(ctx.scene, train_cameras=self.depth_cameras), masks, opts,
                                          cache_dir=self._run_dir(ctx) / "canonical",
                                          progress=not ctx.args.run.quiet, anchors=anchors)
            static, dynamic, times, groups, described = self._compose(ctx, space, masks)
            residual = prior_residual(space.report["alignment"].get("fits") or {},
                                      self.info.get("disparity_field", {}).get("held_out", {}))
            check = check_initial_cloud(static.points, groups, ctx.train_cameras, anchors, residual,
                                        self.p.canonical_max_fit_residual, self.p.canonical_max_depth_error)
            if check.passed or keep:
                break
            failures.append(f"{what}: {check.failure}")
            if check.measurements.get("depth_prior_rejected"):  # the fits alone share the same depth prior
                space = None
                break
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

        static, cameras = space.static, self.depth_cameras
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
                                           self.p.relative_time, self.p.anchor_keyframes, self.p.window_cull)
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
            self._scale_dynamic_branch(model)
            if dynamic:
                model.deformation.fit_box(model.get_xyz.detach()[model.deformation_table], self.p.dynamic_aabb_margin)
            else:
                log.warning("separation: no Gaussian is labelled dynamic, so the scene is modelled as static "
                            "(label_source=%s; motion masks: %s)", self.p.label_source, self.info.get("mask_source"))
        self._record(ctx)

    def _scale_dynamic_branch(self, model: GaussianModel) -> None:
        """The dynamic branch's learning rates (`_dynamic_lr_multiplier`) and position scale.

        Above the extent cap the rates stop growing with the extent; with `dynamic_scale_free` the
        position deltas are multiplied by extent / cap instead (a reparametrisation, exact for the
        branch: its inputs are normalised to the dynamic box, its loss gradients scale as 1 / extent),
        so a scene at scale 50 trains its motion as the same scene at extent `cap` would, not 50x
        more slowly relative to its size (README, "Real priors": truck).
        """
        for group in ("deformation", "grid"):
            model.scale_learning_rate(group, self._dynamic_lr_multiplier(model))
        extent, cap = float(model.spatial_lr_scale), self.p.dynamic_lr_extent_cap
        scale = extent / cap if self.p.dynamic_scale_free and cap > 0 and extent > cap else 1.0
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
            self._scale_dynamic_branch(ctx.model)
        table = ctx.model.deformation_table
        self.info["labels"] = {"dynamic": int(table.sum()), "static": int((~table).sum())}

    def on_stage_start(self, ctx) -> None:
        means = ctx.model.get_xyz.detach()
        cam = ctx.train_cameras[0]
        z = means @ cam.viewmat[:3, :3].T[:, 2] + cam.viewmat[2, 3]
        z = z[z > 0]
        self.scene_depth = float(z.median()) if z.numel() else 1.0
        if self.sampler is not None and self.p.pair_max_motion > 0 and self.sampler.motion is None:
            self._limit_pair_motion(ctx.train_cameras)
        if ctx.stage == "fine" and self.p.dynamic_warmup > 0 and self.is_enabled("separation"):
            ctx.model.freeze(["deformation", "grid"])
        self.coarse_fitted = self.coarse_fitted or (ctx.stage == "coarse" and ctx.args.opt.coarse_iterations > 0)
        flagged = self._missed_motion(ctx)  # rendered while the dynamic Gaussians are still hidden
        self._hide_dynamic_in_coarse(ctx)
        if flagged is not None:
            self._promote(ctx, flagged)
        if (ctx.stage == "fine" and self.p.box_labels and self.is_enabled("separation")
                and self.info.get("mask_source") == "estimated"):
            self._label_box(ctx)

    def _label_box(self, ctx) -> None:
        """`box_labels`: every Gaussian inside the dynamic branch's box becomes dynamic."""
        model = ctx.model
        high, low = model.deformation.get_aabb
        means = model.get_xyz.detach()
        inside = ((means >= low.to(means.device)) & (means <= high.to(means.device))).all(1)
        before = int(model.deformation_table.sum())
        model.set_deformation_table(model.deformation_table | inside.to(model.deformation_table.device))
        self.info["box_labels"] = {"before": before, "dynamic": int(model.deformation_table.sum())}
        log.info("box labels: %d -> %d dynamic Gaussians", before, self.info["box_labels"]["dynamic"])

    def _missed_motion(self, ctx) -> list[np.ndarray] | None:
        """Fine-stage start, estimated masks, `promote_residual` > 0: the coarse fit's flagged pixels."""
        if (ctx.stage != "fine" or self.p.promote_residual <= 0 or not self.is_enabled("separation")
                or self.masks is None or self.info.get("mask_source") != "estimated"
                or not self.coarse_fitted):  # no coarse fit here (none asked, or resumed in the fine stage)
            return None
        return missed_motion_maps(ctx.model, ctx.train_cameras, self.masks, ctx.background,
                                  self.p.promote_residual, backend=ctx.args.pipe.backend)

    def _promote(self, ctx, flagged: list[np.ndarray]) -> None:
        model = ctx.model
        promoted = torch.from_numpy(promoted_gaussians(model, ctx.train_cameras, flagged, self.p.label_vote))
        table = model.deformation_table.cpu() | promoted
        model.set_deformation_table(table)
        if bool(promoted.any()):
            model.deformation.fit_box(model.get_xyz.detach()[model.deformation_table], self.p.dynamic_aabb_margin)
        share = float(np.mean([f.mean() for f in flagged]))
        self.info["promotion"] = {"promoted": int(promoted.sum()), "dynamic": int(table.sum()),
                                  "flagged_pixel_share": share}
        log.info("promotion: %d static Gaussians made dynamic (%.1f%% of unmasked pixels flagged by the coarse "
                 "fit's residual)", int(promoted.sum()), 100 * share)
        self._record(ctx)

    def _relabel(self, ctx) -> None:
        """Static Gaussians the residual votes call moving become dynamic (promotion.py: ResidualVotes)."""
        model = ctx.model
        promoted = self.relabel.promote(model, self.p.label_vote, self.p.relabel_min_views)
        count = int(promoted.sum())
        rounds = self.info.setdefault("relabel", [])
        rounds.append({"iteration": ctx.iteration, "promoted": count})
        if count:
            model.set_deformation_table(model.deformation_table | promoted.to(model.deformation_table.device))
            rounds[-1]["dynamic"] = int(model.deformation_table.sum())
            log.info("relabel at fine iteration %d: %d static Gaussians made dynamic (%d dynamic now)",
                     ctx.iteration, count, rounds[-1]["dynamic"])

    def _limit_pair_motion(self, cameras) -> None:
        """Partners only among frames whose cameras move at most pair_max_motion x the median motion
        between neighbouring training frames (pairs.py: `limit_motion`)."""
        n = len(cameras)
        motion = np.zeros((n, n))
        for i in range(n):
            for j in range(n):
                if i != j:
                    motion[i, j] = camera_motion_pixels(cameras[j].K, cameras[i].viewmat, cameras[j].viewmat,
                                                        self.scene_depth)
        order = self.sampler.order
        neighbours = [motion[order[p], order[p + 1]] for p in range(n - 1)]
        limit = self.p.pair_max_motion * float(np.median(neighbours))
        self.sampler.limit_motion(motion, limit)
        self.info["pair_max_motion_px"] = limit

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
                ctx.hidden = dynamic.clone()
            elif ctx.stage == "fine" and HIDDEN_OPACITY in model.registered_buffers:
                saved = model.pop_gaussian_buffer(HIDDEN_OPACITY)
                model._opacity[dynamic] = saved[dynamic]
                ctx.hidden = None

    # ------------------------------------------------------------------ per iteration
    def select_batch(self, ctx) -> list | None:
        if self.sampler is None or not self.renders_both:
            return None
        if ctx.stage == "fine" and self._uses_curriculum:
            i, j = self.sampler.sample(*self._curriculum_span(ctx))
        else:
            i, j = self.sampler.sample()
        return [ctx.train_cameras[i], ctx.train_cameras[j]]

    def _curriculum_span(self, ctx) -> tuple[int, int]:
        """(reference position, allowed radius) of the curriculum at this iteration."""
        total = int(self.p.curriculum_fraction * ctx.stage_iterations)
        position = self.sampler.position[self.reference]
        span = max(position, self.sampler.num_frames - 1 - position)
        return position, curriculum_radius(ctx.iteration, total, span)

    def select_partners(self, ctx) -> list | None:
        """`pair_mode partner`: a nearby frame b for each view of the host's batch; b is projected
        (not rendered) when this iteration renders full flow, else only its camera is used."""
        self._partner_cameras, self._partners_projected = [], False
        if self.sampler is None or self.renders_both or not self._flow_step(ctx):
            return None
        index = {c.uid: i for i, c in enumerate(ctx.train_cameras)}
        lo, hi = 0, self.sampler.num_frames - 1
        if ctx.stage == "fine" and self._uses_curriculum:
            center, radius = self._curriculum_span(ctx)
            lo, hi = max(0, center - radius), min(hi, center + radius)
        for camera in ctx.batch:
            i = index.get(camera.uid)
            inside = i is not None and lo <= self.sampler.position[i] <= hi
            j = self.sampler.partner(i, lo, hi) if inside else None
            self._partner_cameras.append(None if j is None else ctx.train_cameras[j])
        chosen = [c for c in self._partner_cameras if c is not None]
        self._partners_projected = bool(chosen) and self._full_now(ctx)
        return chosen if self._partners_projected else None

    def extra_features(self, ctx, view_index: int) -> dict[str, Tensor] | None:
        targets = self._targets(ctx)
        full, cam = self._flags(ctx)
        features: dict[str, Tensor] = {}
        for (k, _, target), use_full, use_cam in zip(targets, full, cam):
            if k != view_index:
                continue
            if target is not None and self._full_now(ctx):
                channels = flow_features(ctx.views[k].projection, target.projection)
                if not self.p.full_flow_static_grad and self.is_enabled("separation"):
                    channels = torch.where(self._dynamic(ctx).unsqueeze(1), channels, channels.detach())
                features[FLOW_KEY] = channels
            dynamic_terms = use_full and (self.config.full_flow_dynamic_only or self.config.blur_dynamic_only)
            if use_cam or dynamic_terms:
                features[DYNAMIC_KEY] = self._dynamic(ctx).to(ctx.views[k].colors.dtype).unsqueeze(1)
        return features or None

    def loss_weights(self, ctx, view_index: int) -> Tensor | None:
        if ctx.stage != "coarse" or not self.p.coarse_static_only or not self.mask_tensors:
            return None
        mask = self.mask_tensors.get(ctx.views[view_index].camera.uid)
        return None if mask is None else (~mask).float().unsqueeze(-1)

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

    def extra_losses(self, ctx) -> dict[str, Tensor] | None:
        full, cam = self._flags(ctx)
        use_ext = self.is_enabled("ext_flow") and self._full_now(ctx)
        if not (any(full) or any(cam) or use_ext):
            self._last = None
            return None
        pairs = self._flow_pairs(ctx, cam)
        result = flow_losses(pairs, self.config, full, cam,
                             lambda k, sigma: (self._blurred_image(pairs[k].target, sigma),
                                               self._blurred_image(pairs[k].source.camera, sigma)))
        if use_ext:
            result.losses["ext"] = self.p.lambda_ext * self._external_loss(pairs)
        ctx.metrics.update(result.metrics)
        dynamic = self._dynamic(ctx)
        if bool(dynamic.any()):
            ctx.metrics["dynamic_opacity"] = float(torch.sigmoid(ctx.model._opacity.detach()[dynamic]).mean())
        self._last = (result, pairs)
        return result.losses

    def _external_loss(self, pairs: list[FlowPair]) -> Tensor:
        """Every direction's L1 to the cached DIS flow (reflow_plugin.external)."""
        if self.external is None:
            self.external = ExternalFlowCache(self._run_dir_path / "external_flow")
        terms = []
        for pair in pairs:
            a = pair.source
            flow, valid = full_flow(a.extras[FLOW_KEY], a.alpha, self.p.flow_min_alpha)
            flow_ext, confident = self.external.get(a.camera, pair.target)
            terms.append(external_flow_loss(flow, valid, flow_ext, confident))
        return torch.stack(terms).mean()

    def _relabels(self, ctx) -> bool:
        """`relabel_every`: fine stage, separation on, ESTIMATED masks (a dataset's masks are trusted)."""
        return (self.relabel is not None and ctx.stage == "fine" and self.is_enabled("separation")
                and self.info.get("mask_source") == "estimated")

    def post_backward(self, ctx) -> None:
        if not self.is_enabled("separation"):
            return
        if self._relabels(ctx):  # before densification: the views' rows are the model's rows
            for view in ctx.views:
                self.relabel.accumulate(ctx.model, view, self.mask_tensors.get(view.camera.uid))
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
        if (self._relabels(ctx) and ctx.iteration % self.p.relabel_every == 0
                and ctx.iteration <= ctx.args.opt.densify_until_iter):
            self._relabel(ctx)
        if self.p.dynamic_warmup > 0 and ctx.iteration == self.p.dynamic_warmup and self.is_enabled("separation"):
            ctx.model.unfreeze(["deformation", "grid"])
        every = self.p.flow_vis_every
        if every and self._last is not None and (ctx.iteration % every == 0 or ctx.iteration == ctx.stage_iterations):
            result, pairs = self._last
            direction, pair = result.directions[0], pairs[0]
            if direction.flow is not None:
                a, b = pair.source.camera, pair.target
                write_panel(self._run_dir(ctx) / "flow_vis" / f"{ctx.iteration:06d}_{a.image_name}_{b.image_name}.png",
                            a.image.cpu().numpy(), direction.warped.detach().cpu().numpy(),
                            b.image.cpu().numpy(), direction.valid.cpu().numpy(),
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
