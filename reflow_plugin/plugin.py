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
    protected_gaussians  dynamic Gaussians never pruned
    on_iteration_end     flow-matching panels (flow_vis_every)
    on_load              a 4DGS folder (--start_checkpoint): labels from deformation magnitude (upgrade.py)
    on_stage_end         fine stage: flow metrics against ground truth when the dataset has it

The hooks are a thin adapter; the work is in one module per section of the paper, mixed into
the class (each module's docstring lists the plugin state it reads and sets):
    canonical_construction.py   3.2.1  initial cloud: canonical space (checked) or host cloud + seeds
    separated_modeling.py       3.2.2  dynamic branch scale and windows, static-first coarse stage
    flow_matching.py            3.3    flow directions and pairs of an iteration (losses: matching.py)

Skips (only what the scene calls for): camera flow on pairs whose cameras barely move; the
dynamic branch when no Gaussian is dynamic (SeparatedDeformation); flow channels and pairs when
both flow losses are disabled (the host's own sampling then).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from torch import Tensor

from baselines.data import PointCloud
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.plugins import Plugin
from baselines.native_build import switched_off_by_env

from .canonical_construction import CanonicalConstruction, _metric_points, canonical_available
from .evaluate import flow_metrics, summary_line, write_flow_metrics
from .external import ExternalFlowCache
from .flow import flow_features
from .flow_matching import FlowMatching
from .labels import aligned_depths, training_masks
from .matching import DYNAMIC_KEY, FLOW_KEY, MatchingConfig, check_occlusion_mode, flow_losses
from .pairs import PairSampler
from .params import (DYNAMIC_AABB_MARGIN, DYNAMIC_INIT_OPACITY, FLOW_MIN_ALPHA, OCCLUSION_ALPHA1, OCCLUSION_ALPHA2,
                     PHOTO_SSIM_WEIGHT, WINDOW_CULL, ReFlowParams, flow_finest_from_env, flow_spread_from_env,
                     resolve_static_decoder)
from .separated_modeling import SeparatedModeling
from .separation import SeparatedDeformation
from .upgrade import upgrade_4dgs_model, written_by_reflow
from .visualize import write_panel

log = logging.getLogger("reflow")
RUN_FOLDER = "reflow"
PARTNER_ROWS_SWITCH = "REFLOW4DGS_PARTNER_ROWS"  # 0/false/off/no: partners deformed whole (partner_rows)
# 0/false/off/no: the static field evaluated at the partner's own time (partner_shared_rows)
PARTNER_STATIC_SWITCH = "REFLOW4DGS_PARTNER_STATIC_SHARED"


class ReFlowPlugin(CanonicalConstruction, SeparatedModeling, FlowMatching, Plugin):
    name = "reflow"
    components = ("comp_init", "separation", "full_flow", "cam_flow", "occlusion", "cam_occlusion", "ext_flow")
    default_disabled = ("occlusion", "cam_occlusion", "ext_flow")
    param_groups = {"ReFlowParams": ReFlowParams}
    outputs = (RUN_FOLDER, "flow", "flow_metrics.json")  # what --overwrite clears of a ReFlow run

    def __init__(self, params: Mapping[str, Any] | None = None, enabled: frozenset[str] | None = None) -> None:
        super().__init__(params, enabled)
        self.p: ReFlowParams = self.params.get("ReFlowParams") or ReFlowParams()
        self.static_decoder = resolve_static_decoder(self.p.static_decoder, self.is_enabled("separation"))
        flow_spread_from_env(), flow_finest_from_env()  # bad values are refused here, before any data is read
        self.sampler: PairSampler | None = None
        self.masks: list[np.ndarray] | None = None  # per training camera (uid order), True = dynamic
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
            cross_time_ratio=self.p.cross_time_ratio, ssim_weight=PHOTO_SSIM_WEIGHT,
            min_alpha=FLOW_MIN_ALPHA, blur_sigmas=tuple(self.p.flow_blur_sigmas),
            occlusion=self.is_enabled("occlusion"), occlusion_alpha1=OCCLUSION_ALPHA1,
            occlusion_alpha2=OCCLUSION_ALPHA2, cam_occlusion=self.is_enabled("cam_occlusion"),
            # without separation there is no static/dynamic model to split the pixels by: all pixels
            full_flow_dynamic_only=self.p.full_flow_region == "dynamic" and self.is_enabled("separation"),
            full_flow_min_share=self.p.full_flow_min_share,
            cam_target_static=True)  # the paper masks both sides (measured neutral: +0.02 dB)
        self._blur_cache: dict[tuple[str, float], Tensor] = {}
        self._camera_motion: dict[tuple[int, int], float] = {}
        self._any_dynamic: tuple[Tensor, bool] | None = None  # (labels tensor, any dynamic): _has_dynamic
        self._partner_cameras: list = []  # pair_mode partner: per batch view, its frame b (or None)
        self._partners_projected = False
        self._run_dir_path = Path(".")
        self._last = None
        self.external: ExternalFlowCache | None = None

    # ------------------------------------------------------------------ helpers
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
        self.info["static_decoder"] = self.static_decoder
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

    def build_model(self, ctx) -> GaussianModel | None:
        if not self.is_enabled("separation"):
            return None
        deformation = SeparatedDeformation(ctx.args.hidden, self.static_decoder, zero_init=True, relative_time=True,
                                           anchored=True, window_cull=WINDOW_CULL)
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
                value = torch.logit(torch.tensor(DYNAMIC_INIT_OPACITY).clamp(1e-4, 1 - 1e-4))
                model._opacity[model.deformation_table] = value
            self._register_windows(model)
        if self.is_enabled("separation"):
            self._scale_dynamic_branch(model)
            if dynamic:
                model.deformation.fit_box(model.get_xyz.detach()[model.deformation_table], DYNAMIC_AABB_MARGIN)
            else:
                log.warning("separation: no Gaussian is labelled dynamic, so the scene is modelled as static "
                            "(label_source=%s; motion masks: %s)", self.p.label_source, self.info.get("mask_source"))
        self._record(ctx)

    def on_load(self, ctx, point_cloud_dir) -> None:
        source = self.p.upgrade_labels
        if source == "motion" or (source == "auto" and not written_by_reflow(point_cloud_dir)):
            times = sorted({float(c.time) for c in ctx.train_cameras})
            self.info["upgrade"] = upgrade_4dgs_model(ctx.model, times, self.p.upgrade_motion_threshold,
                                                      ctx.scene.cameras_extent, bake=self._bakes_static())
            log.info("upgraded %s: %d dynamic, %d static Gaussians (motion > %.4g world units)", point_cloud_dir,
                     self.info["upgrade"]["dynamic"], self.info["upgrade"]["static"],
                     self.info["upgrade"]["threshold_world"])
        if self.is_enabled("separation"):
            self._scale_dynamic_branch(ctx.model)
        table = ctx.model.deformation_table
        self.info["labels"] = {"dynamic": int(table.sum()), "static": int((~table).sum())}

    def _bakes_static(self) -> bool:
        """Whether an upgraded 4DGS model's static Gaussians are frozen at their time averages: with
        separation, unless the static field carries 4DGS's own network (`complete_foreign_state`)."""
        return self.is_enabled("separation") and self.static_decoder != "field"

    def on_stage_start(self, ctx) -> None:
        # again here: a run continued from a point_cloud folder or a checkpoint builds no initial cloud
        check_occlusion_mode(self.config.occlusion, self.config.cam_occlusion, self.p.pair_mode)
        means = ctx.model.get_xyz.detach()
        cam = ctx.train_cameras[0]
        z = means @ cam.viewmat[:3, :3].T[:, 2] + cam.viewmat[2, 3]
        z = z[z > 0]
        self.scene_depth = float(z.median()) if z.numel() else 1.0
        self._hide_dynamic_in_coarse(ctx)

    # ------------------------------------------------------------------ per iteration
    def select_batch(self, ctx) -> list | None:
        if self.sampler is None or not self.renders_both:
            return None
        if ctx.stage == "fine" and self._uses_curriculum:
            i, j = self.sampler.sample(*self._curriculum_span(ctx))
        else:
            i, j = self.sampler.sample()
        return [ctx.train_cameras[i], ctx.train_cameras[j]]

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

    def partner_rows(self, ctx) -> list[Tensor | None] | None:
        """Per projected partner: the Gaussians its batch view can show at the view's time
        (SeparatedDeformation.alive_at). A partner's projection is read only through that view's flow
        channels, and a Gaussian the view cannot show never reaches its pixels, so its state at the
        partner's time changes neither values nor gradients: it stays undeformed (about 25% of the
        partner rows on NVIDIA Balloon1 `-r 4`, whose keyframe copies live in short temporal windows).
        `REFLOW4DGS_PARTNER_ROWS=0` deforms them whole (for A/B measurements)."""
        alive_at = getattr(ctx.model.deformation, "alive_at", None)
        if not self._partners_projected or alive_at is None or switched_off_by_env("", PARTNER_ROWS_SWITCH):
            return None
        buffers = ctx.model.deformation_inputs()
        views = [view for view, partner in zip(ctx.batch, self._partner_cameras) if partner is not None]
        return [alive_at(view.time, buffers) for view in views]

    def partner_shared_rows(self, ctx) -> list[tuple[int, Tensor] | None] | None:
        """With the static field: per projected partner, (its batch view, the static Gaussians). They
        take the field's value at the VIEW's time at the partner too, so a static Gaussian's flow
        towards the partner is the camera's alone, and the field (4DGS's whole network, on most rows)
        runs once per view instead of twice (measured: suite means within 0.05 dB, the step 2.1-2.5x
        -> 1.6-1.7x the baseline's; docs/PROFILE.md and docs/REAL_CAPTURES.md, "The static field
        read once per view"). Values and gradients of the views' renders are unchanged.
        `REFLOW4DGS_PARTNER_STATIC_SHARED=0` evaluates the field at the partner's time (A/B)."""
        if (not self._partners_projected or self.static_decoder != "field" or not self.is_enabled("separation")
                or switched_off_by_env("", PARTNER_STATIC_SWITCH)):
            return None
        static = ~ctx.model.deformation_table
        return [(k, static) for k, partner in enumerate(self._partner_cameras) if partner is not None]

    def extra_features(self, ctx, view_index: int) -> dict[str, Tensor] | None:
        targets = self._targets(ctx)
        full, cam = self._flags(ctx)
        features: dict[str, Tensor] = {}
        for (k, _, target), use_full, use_cam in zip(targets, full, cam):
            if k != view_index:
                continue
            if target is not None and self._full_now(ctx):
                channels = flow_features(ctx.views[k].projection, target.projection)
                features[FLOW_KEY] = channels
            dynamic_terms = use_full and self.config.full_flow_dynamic_only
            if use_cam or dynamic_terms:
                features[DYNAMIC_KEY] = self._dynamic(ctx).to(ctx.views[k].colors.dtype).unsqueeze(1)
        return features or None

    def loss_weights(self, ctx, view_index: int) -> Tensor | None:
        if ctx.stage != "coarse" or not self.mask_tensors:
            return None
        mask = self.mask_tensors.get(ctx.views[view_index].camera.uid)
        return None if mask is None else (~mask).float().unsqueeze(-1)

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

    def post_backward(self, ctx) -> None:
        if not self.is_enabled("separation"):
            return
        settling = ctx.stage == "fine" and ctx.iteration <= self.p.dynamic_settle_fraction * ctx.stage_iterations
        frozen = ctx.stage == "coarse" or settling
        dynamic = self._dynamic(ctx)
        if frozen and bool(dynamic.any()):
            ctx.model.zero_row_gradients(dynamic)

    def protected_gaussians(self, ctx) -> Tensor | None:
        if self.is_enabled("separation"):
            return self._dynamic(ctx)
        return None

    def on_iteration_end(self, ctx) -> None:
        if ctx.stage != "fine":
            return
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
