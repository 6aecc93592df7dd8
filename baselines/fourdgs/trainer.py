"""The two-stage 4DGS training loop with plugin hooks.

Behaviour follows hustvl/4DGaussians' train.py: a coarse stage (no deformation) then a fine stage
(HexPlane deformation), each with a fresh optimizer; per iteration: learning-rate schedule, SH
degree warm-up every 1000 iterations, a batch of cameras, L1 (+ optional D-SSIM) loss, HexPlane
regularisation in the fine stage, backward, densification (before the optimizer step, as 4DGS
does), optimizer step. The hook points and their order are listed in hooks.py.

Differences from 4DGS, on purpose: the camera sampler and global RNG states are saved in training
checkpoints (a resumed run continues exactly like an uninterrupted one); the optimizer also steps
on a stage's last iteration; files are written atomically, iteration folders whole (checkpoint.py).
A checkpoint records the plugins and components that wrote it, and resuming it under others is an
error naming both (run_folder.py). Ctrl-C stops after the current iteration with a checkpoint
(interrupt.py). The Gaussians' rows are kept in spatial order, a memory layout only (row_order.py).
"""
from __future__ import annotations

import logging
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from baselines.data import SceneInfo, initial_point_cloud
from baselines.metrics import psnr, ssim, ssim_map

from .checkpoint import (
    FolderContentError,
    find_latest_iteration,
    load_point_cloud_dir,
    point_cloud_dir,
    load_training_state,
    save_point_cloud_dir,
    save_training_state,
)
from .densification import densification_step
from .final_stretch import final_stretch
from .gaussian_model import GaussianModel
from .hooks import HookRunner, TrainContext
from .interrupt import StopFlag, deferred_interrupt
from .plugins import Plugin, PluginError
from .renderer import composite_view, prepare_views, render
from .row_order import order_rows
from baselines.thread_policy import release_free_memory
from baselines.run_folder import (RunFolder, RunIdentity, TrainingInterrupted, check_resume_identity,
                                  check_upgrade_plugins)
from .run_log import RunLog, StageTimer
from .sampler import CameraSampler
from .stall_guard import StallGuard

log = logging.getLogger(__name__)
STAGES = ("coarse", "fine")


@dataclass
class TrainResult:
    """Outcome of a training run."""

    model_path: Path
    final_iteration: int
    num_gaussians: int
    wall_seconds: float
    test_psnr: float | None = None
    timings: dict[str, float] = field(default_factory=dict)


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; otherwise the named device (validated)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name!r} requested but CUDA is not available")
    return device


def peak_rss_mib() -> float:
    """Peak resident memory of this process in MiB (ru_maxrss: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def _max_abs(tensors: list[Tensor]) -> Tensor:
    """max |x| over all tensors (NaN if any entry is NaN): one fused pass where torch has one."""
    try:
        from torch.nn.utils import get_total_norm  # torch >= 2.6
    except ImportError:
        return torch.stack([t.detach().abs().max() for t in tensors]).max()
    return get_total_norm(tensors, norm_type=float("inf"))


class Trainer:
    """Runs the coarse and fine stages on a loaded scene with the given plugins.

    Args:
        args: parsed TrainArgs (parameter groups + run flags).
        scene: the loaded dataset (cameras in our convention).
        plugins: instantiated plugins, called in order.
        model_path: output directory (created).
    """

    QUICK_EVAL_VIEWS = 8  # views per split of the intermediate test events

    def __init__(self, args: Any, scene: SceneInfo, plugins: list[Plugin], model_path: Path) -> None:
        self.args = args
        self.opt = args.opt
        self.hidden = args.hidden
        self.pipe = args.pipe
        self.run = args.run
        self.device = resolve_device(self.pipe.device)
        self.hooks = HookRunner(plugins)
        model_path.mkdir(parents=True, exist_ok=True)
        bg = [1.0, 1.0, 1.0] if args.model.white_background else [0.0, 0.0, 0.0]
        self.ctx = TrainContext(
            args=args, scene=scene, device=self.device, model_path=model_path,
            background=torch.tensor(bg, dtype=torch.float32, device=self.device),
        )
        self.train_cameras = [c.to(self.device) for c in scene.train_cameras]
        self.test_cameras = [c.to(self.device) for c in scene.test_cameras]
        self.ctx.train_cameras, self.ctx.test_cameras = self.train_cameras, self.test_cameras
        self.cameras_extent = float(scene.nerf_normalization["radius"])
        self.sampler = CameraSampler(self.train_cameras, seed=self.opt.seed)
        self.run_log = RunLog(model_path / "train_log.jsonl", quiet=self.run.quiet)
        self._densify_grads: list[Tensor | None] | None = None
        self.timer = StageTimer()
        self.train_seconds = 0.0  # wall / CPU seconds spent in training steps (a resume continues its checkpoint's)
        self.train_cpu_seconds = 0.0
        self.run_folder: RunFolder | None = None  # set by the app: run.json records saves and the end
        self._stop: StopFlag | None = None
        self.stall_guard = StallGuard(0)  # armed by train() for a run that starts from its initial cloud
        self.nonfinite_steps, self._nonfinite_in_a_row = 0, 0  # skipped steps (_gradients_finite)

    def identity(self) -> RunIdentity:
        """The plugins and active components of this run (what a checkpoint must match to resume)."""
        plugins = self.hooks.plugins
        return RunIdentity.of([p.name for p in plugins], {p.name: p.enabled for p in plugins},
                              self.args.model.source_path)

    # ------------------------------------------------------------------ set-up
    def build(self) -> None:
        """Initial point cloud and model (plugins may replace either), before any training."""
        ctx = self.ctx
        self.hooks.call("on_scene_loaded", ctx)
        cloud, source = initial_point_cloud(ctx.scene, seed=self.opt.seed,
                                            check_dataset_points=not self.args.model.force_dataset_points)
        ctx.point_cloud, ctx.point_cloud_source = cloud, source
        replacement = self.hooks.first("initial_point_cloud", ctx)
        if replacement is not None:
            ctx.point_cloud, ctx.point_cloud_source = replacement, "plugin"
        model = self.hooks.first("build_model", ctx)
        if model is None:
            model = GaussianModel(self.args.model.sh_degree, self.hidden)
        model.create_from_pcd(ctx.point_cloud.points, ctx.point_cloud.colors, self.cameras_extent, device=self.device)
        ctx.model = model
        self._set_time_span(model)
        self.hooks.call("on_model_created", ctx)
        order_rows(model)  # after the plugins: their per-Gaussian buffers are registered by now
        self.run_log.event("model_created", num_gaussians=model.num_gaussians, point_cloud_source=ctx.point_cloud_source)

    def _set_time_span(self, model: GaussianModel) -> None:
        """Give the model the training views' time span and `--time_outside`; warn about the test
        views outside that span (the deformation was never fitted there)."""
        if not self.train_cameras:
            return
        times = [c.time for c in self.train_cameras]
        lo, hi = min(times), max(times)
        mode = self.pipe.time_outside
        model.set_time_span((lo, hi), mode)
        outside = [c.image_name for c in self.test_cameras if not lo <= c.time <= hi]
        if outside:
            log.warning("%d test view(s) lie outside the training views' time span [%.4g, %.4g] (%s): "
                        "--time_outside %s (extrapolate|hold|linear)", len(outside), lo, hi,
                        ", ".join(outside[:5]), mode)
        self.run_log.event("time_span", lo=lo, hi=hi, mode=mode, test_views_outside=outside)

    # ------------------------------------------------------------------ main loop
    def train(self) -> TrainResult:
        """Both stages (or what a --start_checkpoint leaves of them), saving as configured."""
        start = time.perf_counter()
        resume = self._resume_point()
        if self.ctx.model is None:
            self.build()
        if resume is None:  # a fresh run: stop early if it cannot learn (stall_guard.py)
            self.stall_guard = StallGuard(self.opt.stall_iterations)
        with deferred_interrupt() as self._stop:
            for stage in STAGES:
                if resume is not None and STAGES.index(stage) < STAGES.index(resume["stage"]):
                    continue
                total = self.opt.coarse_iterations if stage == "coarse" else self.opt.iterations
                first = 1
                self._begin_stage(stage, total)
                if resume is not None and resume["stage"] == stage:
                    first = self._restore(resume) + 1
                    resume = None
                self._run_stage(stage, first, total)
        result = TrainResult(
            model_path=self.ctx.model_path, final_iteration=self.ctx.iteration, num_gaussians=self.ctx.model.num_gaussians,
            wall_seconds=time.perf_counter() - start, timings=self.timer.means(),
        )
        self.run_log.event("train_end", wall_seconds=result.wall_seconds, timings_ms=result.timings,
                           train_seconds=self.train_seconds, train_cpu_seconds=self.train_cpu_seconds,
                           peak_rss_mib=peak_rss_mib(), nonfinite_steps=self.nonfinite_steps)
        self.run_log.close()
        return result

    def _begin_stage(self, stage: str, total: int) -> None:
        ctx = self.ctx
        ctx.stage, ctx.stage_iterations, ctx.iteration = stage, total, 0
        ctx.model.training_setup(self.opt)
        self.hooks.call("on_stage_start", ctx)
        self.run_log.event("stage_start", stage=stage, iterations=total, num_gaussians=ctx.model.num_gaussians)

    def _run_stage(self, stage: str, first: int, total: int) -> None:
        ctx = self.ctx
        bar = self.run_log.progress(total, first - 1, desc=stage)
        for iteration in range(first, total + 1):
            ctx.iteration = iteration
            wall, cpu = time.perf_counter(), time.process_time()
            self.train_step()
            # training time alone (evaluation and saving excluded): the accuracy-versus-time curve
            self.train_seconds += time.perf_counter() - wall
            self.train_cpu_seconds += time.process_time() - cpu
            bar.update(ctx)
            final = stage == "fine" and iteration == total
            if iteration in self.run.test_iterations or final:
                # the final figure is over every test view: the one results.json reports
                self.run_log.event("test", stage=stage, iteration=iteration, train_seconds=self.train_seconds,
                                   train_cpu_seconds=self.train_cpu_seconds, **self.quick_eval(all_test_views=final))
            if iteration in self.run.save_iterations or iteration == total:
                self.save_point_cloud()
            if iteration in self.run.checkpoint_iterations:
                self.save_checkpoint()
            if self._stop is not None and self._stop.requested:
                bar.close()
                self._stop_here()
        bar.close()
        self.hooks.call("on_stage_end", ctx)

    def train_step(self) -> None:
        """One optimisation step: batch, render, losses, backward, densify, optimizer step."""
        ctx, model, opt = self.ctx, self.ctx.model, self.opt
        model.update_learning_rate(ctx.iteration)
        if ctx.iteration % 1000 == 0:
            model.oneupSHdegree()
        ctx.batch = self.hooks.first("select_batch", ctx) or self.sampler.next_batch(opt.batch_size)
        partners = self.hooks.first("select_partners", ctx) or []
        rows = (self.hooks.first("partner_rows", ctx) if partners else None) or [None] * len(partners)
        if len(rows) != len(partners):
            raise PluginError(f"partner_rows returned {len(rows)} masks for {len(partners)} partner cameras")
        shared = (self.hooks.first("partner_shared_rows", ctx) if partners else None) or [None] * len(partners)
        if len(shared) != len(partners) or any(s is not None and not 0 <= s[0] < len(ctx.batch) for s in shared):
            raise PluginError(f"partner_shared_rows must give, per partner camera ({len(partners)}), None or "
                              f"(index of a batch view < {len(ctx.batch)}, [N] bool); got {len(shared)} entries")
        ctx.losses, ctx.metrics, ctx.densify_record = {}, {}, None

        with self.timer("deform_project"):
            # one deformation call for the batch and the partner frames (prepare_views)
            prepared = prepare_views(model, [*ctx.batch, *partners], ctx.stage, self.pipe.backend,
                                     [True] * len(ctx.batch) + [False] * len(partners),
                                     [None] * len(ctx.batch) + list(rows), [None] * len(ctx.batch) + list(shared))
            ctx.views, ctx.partners = prepared[:len(ctx.batch)], prepared[len(ctx.batch):]
        with self.timer("rasterize"):
            for k, view in enumerate(ctx.views):
                extra = self.hooks.merged("extra_features", ctx, k, prefix=False)
                composite_view(view, ctx.background, extra, self.pipe.backend)

        with self.timer("loss_backward"):
            baseline = self.baseline_losses()
            ctx.losses.update(baseline)
            extra = self.hooks.merged("extra_losses", ctx)
            ctx.losses.update(extra)
            ctx.loss = torch.stack([v.reshape(()) for v in ctx.losses.values()]).sum()
            if not torch.isfinite(ctx.loss):
                bad = [k for k, v in ctx.losses.items() if not torch.isfinite(v).all()]
                raise FloatingPointError(f"non-finite loss at {ctx.stage} iteration {ctx.iteration}: {bad}")
            self.hooks.call("pre_backward", ctx)
            self._densify_grads = self._baseline_screen_grads(baseline) if extra else None
            ctx.loss.backward()
            self.hooks.call("post_backward", ctx)

        with self.timer("densify_step"):
            count = model.num_gaussians
            with torch.no_grad():
                if self._gradients_finite():
                    self._densify()
                    model.optimizer.step()
                model.optimizer.zero_grad(set_to_none=True)
            if model.num_gaussians != count:
                # a new count: the next activations no longer fit the holes the old ones left (thread_policy.py)
                release_free_memory()
        self.hooks.call("on_iteration_end", ctx)
        ctx.metrics.update(
            loss=float(ctx.loss.detach()), num_gaussians=model.num_gaussians,
            psnr=float(torch.stack([psnr(v.image.detach(), v.camera.image) for v in ctx.views]).mean()),
        )
        self.stall_guard.observe(ctx)
        self.run_log.iteration(ctx, every=self.run.log_every)

    def _gradients_finite(self) -> bool:
        """True when every gradient is finite; else the step is skipped, or the run stopped.

        Adam turns one NaN gradient into NaN parameters for good, and the run then fails later,
        far from the cause (the rasterizer's input check), or finishes with a broken model. A rare
        non-finite step (one Gaussian's deformed covariance overflowing in one view pair) is skipped
        instead, like mixed-precision loss scaling does: nothing is updated, the densification
        statistic is not accumulated. The first skipped step's state (parameters before it,
        optimizer, the views it drew) is written to nonfinite_<stage>_<iteration>.pth so the cause
        can be found; more than --nonfinite_skips such steps in a row stop the run with the culprit.
        """
        ctx, optimizer = self.ctx, self.ctx.model.optimizer
        # The HexPlane planes (36M values in 4DGS's default model) are left out: their gradient is
        # the lookup's, whose incoming gradient also reaches feature_out's weights (checked), and
        # scanning them cost a third of the optimizer step.
        grads = [p.grad for group in optimizer.param_groups if group["name"] != "grid"
                 for p in group["params"] if p.grad is not None]
        # one fused pass (max |g| is NaN/inf iff some entry is) instead of a check and sync per tensor
        if not grads or bool(torch.isfinite(_max_abs(grads))):
            self._nonfinite_in_a_row = 0
            return True
        bad = [group for group in optimizer.param_groups
               if any(p.grad is not None and not bool(torch.isfinite(p.grad).all()) for p in group["params"])]
        rates = ", ".join(f"{g['name']} (lr {g['lr']:.3g})" for g in bad)
        losses = ", ".join(f"{k} {float(v.detach()):.4g}" for k, v in ctx.losses.items())
        where = f"{ctx.stage} iteration {ctx.iteration}"
        self._nonfinite_in_a_row += 1
        self.nonfinite_steps += 1
        dump = self._save_nonfinite_state() if self.nonfinite_steps == 1 else None
        views = [v.camera.image_name for v in ctx.views] + [p.camera.image_name for p in ctx.partners]
        self.run_log.event("nonfinite_step", stage=ctx.stage, iteration=ctx.iteration, groups=[g["name"] for g in bad],
                           views=views, in_a_row=self._nonfinite_in_a_row, state=str(dump) if dump else None)
        if self._nonfinite_in_a_row > self.opt.nonfinite_skips:
            raise FloatingPointError(
                f"non-finite gradients at {where} in {rates}; losses: {losses} "
                f"({self._nonfinite_in_a_row} steps in a row, --nonfinite_skips {self.opt.nonfinite_skips}). "
                f"Learning rates of position, deformation and grid scale with the scene extent "
                f"({ctx.model.spatial_lr_scale:.3g} here); on a large-scale scene lower them (e.g. "
                f"--deformation_lr_init, --grid_lr_init) or rescale the scene")
        log.warning("non-finite gradients at %s in %s (views %s): step skipped%s", where, rates, ", ".join(views),
                    f"; its state: {dump}" if dump else "")
        return False

    def _save_nonfinite_state(self) -> Path | None:
        """The model before the skipped step and the views it drew: a checkpoint `--start_checkpoint` loads."""
        ctx = self.ctx
        path = ctx.model_path / f"nonfinite_{ctx.stage}_{ctx.iteration}.pth"
        extra = {**self._checkpoint_extra(), "views": [v.camera.image_name for v in ctx.views],
                 "partners": [p.camera.image_name for p in ctx.partners],
                 "losses": {k: float(v.detach()) for k, v in ctx.losses.items()},
                 "grads": {g["name"]: [p.grad.detach().clone() if p.grad is not None else None for p in g["params"]]
                           for g in ctx.model.optimizer.param_groups if g["name"] != "grid"}}
        try:
            return save_training_state(path, ctx.model, ctx.iteration, ctx.stage, extra)
        except OSError as err:  # a diagnosis aid: never the reason a run stops
            log.warning("could not save the non-finite step's state to %s (%s)", path, err)
            return None

    def baseline_losses(self) -> dict[str, Tensor]:
        """4DGS's loss: L1 over the batch, optional D-SSIM, HexPlane regularisers (fine stage).

        Plugins may weight pixels (`loss_weights` hook): L1 and D-SSIM then become weighted means
        over the batch's pixels (equal to 4DGS's means when no plugin returns weights).
        """
        ctx = self.ctx
        renders = torch.stack([v.image for v in ctx.views])
        gts = torch.stack([v.camera.image for v in ctx.views])
        weights = self._pixel_weights(renders)
        if weights is None:
            losses = {"l1": (renders - gts).abs().mean()}
        else:
            total = (weights.sum() * renders.shape[-1]).clamp_min(1e-12)
            losses = {"l1": (weights * (renders - gts).abs()).sum() / total}
        if self.opt.lambda_dssim != 0:
            if weights is None:
                losses["dssim"] = self.opt.lambda_dssim * (1.0 - ssim(renders, gts)).mean()  # ssim: [B]
            else:
                losses["dssim"] = self.opt.lambda_dssim * (1.0 - (weights * ssim_map(renders, gts)).sum() / total)
        if ctx.stage == "fine" and self.hidden.time_smoothness_weight != 0:
            losses["regulation"] = ctx.model.compute_regulation(
                self.hidden.time_smoothness_weight, self.hidden.l1_time_planes, self.hidden.plane_tv_weight
            )
        return losses

    def _pixel_weights(self, renders: Tensor) -> Tensor | None:
        """[B, H, W, 1] product of the plugins' loss weights per view, or None when none gave any."""
        per_view = [self.hooks.product("loss_weights", self.ctx, k) for k in range(len(self.ctx.views))]
        if all(w is None for w in per_view):
            return None
        shape = renders.shape[1:3]
        maps = []
        for k, w in enumerate(per_view):
            if w is None:
                maps.append(renders.new_ones(*shape, 1))
                continue
            w = w.reshape(*shape, 1) if w.numel() == shape[0] * shape[1] else w
            if tuple(w.shape) != (*shape, 1):
                raise ValueError(f"loss_weights of view {k}: expected [H, W, 1] = {[*shape, 1]}, got {list(w.shape)}")
            maps.append(w.to(renders.dtype).detach())
        return torch.stack(maps)

    def _baseline_screen_grads(self, baseline: dict[str, Tensor]) -> list[Tensor | None] | None:
        """d(baseline loss)/d(means2d) per view, when densification must ignore the plugins' losses.

        4DGS densifies where the reconstruction loss moves the projected means; a plugin's loss
        (e.g. flow matching) would inflate that statistic. One extra backward through the
        compositing of each view, only while densification still runs.
        """
        ctx = self.ctx
        if self.opt.densify_grad_from != "baseline" or ctx.iteration >= self.opt.densify_until_iter:
            return None
        means2d = [v.projection.means2d for v in ctx.views]
        if not all(m.requires_grad for m in means2d):
            return None
        total = torch.stack([v.reshape(()) for v in baseline.values()]).sum()
        return list(torch.autograd.grad(total, means2d, retain_graph=True, allow_unused=True))

    def _densify(self) -> None:
        ctx = self.ctx
        views = ctx.views
        grads = self._densify_grads or [v.projection.means2d.grad for v in views]
        if any(g is None for g in grads):  # means2d not in the graph (nothing trainable upstream)
            return
        visible = torch.stack([v.projection.visible for v in views]).any(dim=0)
        radii = torch.stack([v.projection.radii.max(dim=1).values for v in views]).max(dim=0).values
        cam = views[0].camera
        protect = self.hooks.combined_mask("protected_gaussians", ctx)
        ctx.densify_record = densification_step(
            ctx.model, self.opt, ctx.iteration, ctx.stage, self.cameras_extent, visible, radii.float(),
            torch.stack(grads).sum(dim=0), cam.width, cam.height,
            max_gaussians=self.opt.densify_max_gaussians, prune_min_gaussians=self.opt.prune_min_gaussians,
            protect=protect,
            stretch=final_stretch(self.opt, ctx.iteration, ctx.stage, ctx.stage_iterations, self.run.save_iterations),
        )
        record = ctx.densify_record
        if record.skipped:
            self.run_log.event("final_stretch", stage=ctx.stage, iteration=ctx.iteration, skipped=record.skipped,
                               reason="kept (saved/final) iteration ahead: no opacity reset or densification")
        if record.densify_ran or record.prune_ran:
            order_rows(ctx.model)  # the rows were rewritten anyway (row_order.py)
        if record.densify_ran or record.prune_ran or record.opacity_reset:
            self.hooks.call("post_densify", ctx)

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def quick_eval(self, max_views: int | None = None, all_test_views: bool = False) -> dict[str, float]:
        """Mean PSNR / L1 on (up to max_views of) the test cameras and the training cameras.

        ``all_test_views``: every test camera, so test_psnr equals evaluate_cameras' mean PSNR.
        """
        max_views = max_views or self.QUICK_EVAL_VIEWS
        out: dict[str, float] = {}
        for split, cams in (("test", self.test_cameras), ("train", self.train_cameras)):
            if not cams:
                continue
            count = len(cams) if split == "test" and all_test_views else max_views
            step = max(1, len(cams) // count)
            values = []
            for cam in cams[::step][:count]:
                view = render(self.ctx.model, cam, self.ctx.stage, self.ctx.background, self.pipe.backend)
                values.append((float(psnr(view.image.clamp(0, 1), cam.image)), float((view.image - cam.image).abs().mean())))
            out[f"{split}_psnr"] = sum(v[0] for v in values) / len(values)
            out[f"{split}_l1"] = sum(v[1] for v in values) / len(values)
        return out

    # ------------------------------------------------------------------ persistence
    def _stop_here(self) -> None:
        """Ctrl-C was pressed: checkpoint this (consistent) iteration and stop."""
        ctx = self.ctx
        path = ctx.model_path / f"chkpnt_{ctx.stage}_{ctx.iteration}.pth"
        if not path.is_file():
            path = self.save_checkpoint()
        self.run_log.event("interrupted", stage=ctx.stage, iteration=ctx.iteration, checkpoint=str(path),
                           train_seconds=self.train_seconds, train_cpu_seconds=self.train_cpu_seconds)
        raise TrainingInterrupted(ctx.stage, ctx.iteration, path, self._stop.signum if self._stop else 2)

    def save_point_cloud(self) -> Path:
        """point_cloud/(coarse_)iteration_N, written whole (plugins' on_save files included) then renamed."""
        ctx = self.ctx
        path = point_cloud_dir(ctx.model_path, ctx.iteration, ctx.stage)
        save_point_cloud_dir(ctx.model, path, before_publish=lambda staging: self.hooks.call("on_save", ctx, staging))
        if self.run_folder is not None:
            self.run_folder.record_saved(path, ctx.stage, ctx.iteration)
        self.run_log.event("saved", path=str(path))
        return path

    def save_checkpoint(self) -> Path:
        ctx = self.ctx
        path = ctx.model_path / f"chkpnt_{ctx.stage}_{ctx.iteration}.pth"
        save_training_state(path, ctx.model, ctx.iteration, ctx.stage, self._checkpoint_extra())
        if self.run_folder is not None:
            self.run_folder.record_checkpoint(path, ctx.stage, ctx.iteration)
        self.run_log.event("checkpoint", path=str(path))
        return path

    def _checkpoint_extra(self) -> dict:
        """What a checkpoint holds besides the model: RNG, sampler and plugin states, the run's identity."""
        return {
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            "sampler": self.sampler.state_dict(),
            # by name: a resume on another camera list is refused or re-mapped (check_resume_cameras)
            "cameras": {"train": [c.image_name for c in self.train_cameras], "eval": bool(self.args.model.eval)},
            "plugins": self.hooks.state_dict(),
            "run": {"plugins": list(self.identity().plugins),
                    "components": {k: list(v) for k, v in self.identity().components.items()}},
            # the training clock up to this iteration: a resumed run's figures count every chunk
            "clock": {"train_seconds": self.train_seconds, "train_cpu_seconds": self.train_cpu_seconds},
        }

    def load_model_from(self, folder: Path) -> None:
        """Build the model (a plugin may replace it) and load a point_cloud/iteration_N folder.

        Used to continue from a 4DGS output (the upgrade path) and by render.py. No initial cloud
        is computed; plugins get `on_load` (not `on_model_created`) and must (re)create the
        per-Gaussian buffers a 4DGS folder lacks.
        """
        ctx = self.ctx
        self.hooks.call("on_scene_loaded", ctx)
        model = self.hooks.first("build_model", ctx)
        if model is None:
            model = GaussianModel(self.args.model.sh_degree, self.hidden)
        load_point_cloud_dir(folder, model, device=self.device)
        model.spatial_lr_scale = self.cameras_extent
        ctx.model, ctx.point_cloud_source = model, f"checkpoint {folder}"
        self._set_time_span(model)
        self.hooks.call("on_load", ctx, folder)
        self.run_log.event("loaded", path=str(folder), num_gaussians=model.num_gaussians)

    def _resume_point(self) -> dict[str, Any] | None:
        """Interpret --start_checkpoint: a chkpnt_*.pth (exact resume) or a point_cloud dir (upgrade)."""
        spec = self.run.start_checkpoint
        if not spec:
            return None
        path = Path(spec)
        if path.is_dir():
            pc_dir = latest_point_cloud_dir(path)
            check_upgrade_plugins(path, self.identity())
            try:
                self.load_model_from(pc_dir)
            except FolderContentError:
                raise  # a missing or damaged file: no configuration fixes that
            except ValueError as err:
                raise ValueError(f"{err}; {config_hint(path)}") from None
            # A 4DGS output is a trained model: continue in the fine stage from iteration 0.
            return {"stage": "fine", "point_cloud_dir": pc_dir}
        if not path.is_file():
            raise FileNotFoundError(f"--start_checkpoint {spec}: no such file or directory")
        state = load_training_state(path)
        if state.stage not in STAGES:
            raise ValueError(f"--start_checkpoint {spec}: cannot tell its stage; name it chkpnt_<coarse|fine>_<N>.pth")
        check_resume_identity(spec, state.extra, self.identity())
        order = check_resume_cameras(spec, state.extra, [c.image_name for c in self.train_cameras],
                                         bool(self.args.model.eval))
        return {"stage": state.stage, "training_state": state, "path": path, "camera_order": order}

    def _restore(self, resume: dict[str, Any]) -> int:
        """Restore a training state into the freshly set-up stage; return its iteration."""
        if "training_state" not in resume:
            return 0
        state = resume["training_state"]
        self.ctx.model.restore(state.capture, self.opt, device=self.device)
        extra = state.extra or {}
        if extra.get("torch_rng") is not None:
            torch.set_rng_state(extra["torch_rng"])
        if extra.get("cuda_rng") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(extra["cuda_rng"])
        if extra.get("sampler") is not None:
            if resume.get("camera_order") is not None:  # same cameras listed in another order: the saved one
                self.sampler.items = [self.train_cameras[i] for i in resume["camera_order"]]
            self.sampler.load_state_dict(extra["sampler"])
        self.hooks.load_state_dict(extra.get("plugins") or {})
        clock = extra.get("clock")
        if isinstance(clock, dict):  # checkpoints written before the clock was saved start it at 0
            self.train_seconds = float(clock["train_seconds"])
            self.train_cpu_seconds = float(clock["train_cpu_seconds"])
        self.run_log.event("resumed", path=str(resume["path"]), stage=state.stage, iteration=state.iteration,
                           clock_restored=isinstance(clock, dict), train_seconds=self.train_seconds,
                           train_cpu_seconds=self.train_cpu_seconds)
        return int(state.iteration)


def check_resume_cameras(spec: str, extra: dict[str, Any] | None, names: list[str], evaluating: bool) -> list[int] | None:
    """An exact resume trains on the same training cameras: compare the checkpoint's names with this
    run's (`names`, in sampler order). When only the order differs, returns this run's index of each
    checkpoint camera (the sampler then draws from the checkpoint's order: exact); None when nothing
    needs re-mapping; raises ValueError naming what differs otherwise.

    Checkpoints written before the names were recorded are checked by the sampler's indices only."""
    extra = extra or {}
    recorded = extra.get("cameras")
    if not isinstance(recorded, dict) or not isinstance(recorded.get("train"), list):
        stack = [int(i) for i in (extra.get("sampler") or {}).get("stack", [])]
        if stack and max(stack) >= len(names):
            raise ValueError(f"--start_checkpoint {spec} was trained on at least {max(stack) + 1} training cameras, "
                             f"this dataset gives {len(names)}: resume on the dataset (and --eval setting) it was "
                             "trained on")
        return None
    theirs = [str(n) for n in recorded["train"]]
    if theirs == names:
        return None
    if sorted(theirs) == sorted(names) and len(set(names)) == len(names):
        position = {name: i for i, name in enumerate(names)}
        return [position[name] for name in theirs]
    missing = [n for n in theirs if n not in set(names)]
    added = [n for n in names if n not in set(theirs)]

    def listed(items: list[str]) -> str:
        return ", ".join(items[:4]) + (f" (+{len(items) - 4} more)" if len(items) > 4 else "")

    parts = [f"{len(theirs)} training cameras in the checkpoint, {len(names)} here"]
    if missing:
        parts.append(f"not here: {listed(missing)}")
    if added:
        parts.append(f"new here: {listed(added)}")
    hint = "resume on the dataset it was trained on"
    saved_eval = recorded.get("eval")
    if isinstance(saved_eval, bool) and saved_eval != evaluating:
        hint = f"it was trained with {'--eval' if saved_eval else '--no-eval'}: give the same"
    raise ValueError(f"--start_checkpoint {spec}: other training cameras ({'; '.join(parts)}); {hint}")


def config_hint(start_checkpoint: Path) -> str:
    """What to pass when an old output's files do not fit the model this run built."""
    from arguments.saved import model_dir_of_checkpoint, read_saved_configs

    model_dir = model_dir_of_checkpoint(start_checkpoint) or start_checkpoint
    configs = read_saved_configs(model_dir)
    if configs:
        return f"that run was trained with --configs {' '.join(configs)} (from {model_dir}): pass it"
    return (f"{model_dir} records no config file: pass the --configs file it was trained with "
            "(e.g. arguments/dnerf/<scene>.py)")


def latest_point_cloud_dir(path: Path) -> Path:
    """A point_cloud/iteration_N folder itself, or the highest fine iteration of a model folder."""
    if (path / "point_cloud.ply").is_file():
        return path
    latest = find_latest_iteration(path)
    if latest is None:
        raise FileNotFoundError(f"--start_checkpoint {path}: no point_cloud.ply and no point_cloud/iteration_N inside")
    return point_cloud_dir(path, latest)
