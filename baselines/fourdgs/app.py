"""Command-line orchestration shared by train.py and render.py (and callable from tests).

`train_from_argv` turns a train.py command line into a finished run: plugins are resolved first
(they add parameter groups and flags), then flags and config files are parsed, components
toggled, the dataset loaded and checked, the model trained, the held-out views evaluated and the
novel-time video written. Every input check happens before the first training iteration.
"""
from __future__ import annotations

import logging
import os
import random
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from baselines import thread_policy

from .family_config import dataset_family, default_config, family_background, log_decision, strip_bare_defaults
from .evaluate import EvalResult, evaluate_cameras, render_video, write_metrics
from .plugins import Plugin, load_plugin_class, resolve_components
from .trainer import Trainer, TrainResult

REPO_ROOT = Path(__file__).resolve().parents[2]
EMBEDDED_SCENE = "skating"
log = logging.getLogger("train")


@dataclass
class RunSummary:
    """What a train.py run produced."""

    trainer: Trainer
    result: TrainResult
    evaluation: EvalResult | None
    video: Path | None


def embedded_scene_path(root: Path = REPO_ROOT) -> Path:
    """Generate the embedded synthetic scene once (data/synthetic/<name>) and return its path."""
    from baselines.synthetic import get_scene, simulate

    path = root / "data" / "synthetic" / EMBEDDED_SCENE
    if not (path / "poses_bounds.npy").is_file():
        log.info("generating the embedded synthetic scene %r into %s", EMBEDDED_SCENE, path)
        simulate(get_scene(EMBEDDED_SCENE), path)
    return path


def _has_flag(argv: list[str], *names: str) -> bool:
    return any(a == n or a.startswith(n + "=") for a in argv for n in names)


def _flag_value(argv: list[str], *names: str) -> str | None:
    """The last value of a single-valued flag (``-s X`` or ``-s=X``), or None."""
    value = None
    for i, arg in enumerate(argv):
        for name in names:
            if arg == name and i + 1 < len(argv):
                value = argv[i + 1]
            elif arg.startswith(name + "="):
                value = arg.split("=", 1)[1]
    return value


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def build_trainer(argv: list[str]) -> Trainer:
    """Parse, validate and load everything a run needs; return a Trainer ready to train."""
    from arguments import parse_train_args, peek_plugins, write_cfg_args
    from arguments.saved import model_dir_of_checkpoint
    from baselines.data import load_scene

    argv, bare_defaults = strip_bare_defaults(list(argv))
    embedded = not _has_flag(argv, "-s", "--source_path")

    # Plugins first: they contribute parameter groups that the full parse must know.
    plugin_names = peek_plugins(argv)
    plugin_classes = [load_plugin_class(name) for name in plugin_names]
    decision = None
    old_run = model_dir_of_checkpoint(_flag_value(argv, "--start_checkpoint"))
    if not bare_defaults and not _has_flag(argv, "--configs") and old_run is None:
        # 4DGS's bare defaults fit no dataset: the detected family's config (family_config.py);
        # a run continued from an output folder takes that folder's saved configuration instead
        source_flag = _flag_value(argv, "-s", "--source_path") or ""
        source = REPO_ROOT / "data" / "synthetic" / EMBEDDED_SCENE if embedded else Path(source_flag)
        decision = default_config(source, plugin_names, _flag_value(argv, "--dataset_type") or "auto",
                                  family="synthetic" if embedded else None)
        log_decision(decision)
        if decision.path is not None:
            argv += ["--configs", str(decision.path)]
    extra_groups: dict[str, type] = {}
    for cls in plugin_classes:
        extra_groups.update(cls.param_groups)
    args = parse_train_args(argv, extra_groups=extra_groups)
    components = resolve_components(plugin_classes, args.run.disable, args.run.enable)
    seed_everything(args.opt.seed)

    source = embedded_scene_path() if embedded else Path(args.model.source_path)
    args.model.source_path = str(source)
    if args.sources.get("ModelParams.white_background", "default") == "default":
        family = "synthetic" if embedded else dataset_family(source, args.model.dataset_type)
        white = family_background(family)
        if white is not None:
            args.model.white_background = white
            args.sources["ModelParams.white_background"] = f"{family} family"
            log.info("background: %s (%s family; -w / --no-white_background to choose)",
                     "white" if white else "black", family)
    scene = load_scene(
        source, dataset_type=args.model.dataset_type, images=args.model.images,
        resolution=args.model.resolution, eval=args.model.eval,
        white_background=args.model.white_background, llffhold=args.model.llffhold,
    )
    name = args.run.expname or source.name
    model_path = Path(args.model.model_path or REPO_ROOT / "output" / name)
    args.model.model_path = str(model_path)
    model_path.mkdir(parents=True, exist_ok=True)
    write_cfg_args(model_path, args, {"_components": {name: sorted(active) for name, active in components.items()},
                                       "_dataset_layout": scene.metadata.get("layout_detection"),
                                       "_default_config": decision.as_dict() if decision else None})

    plugins: list[Plugin] = [
        cls({g: args.extra[g] for g in cls.param_groups}, components[cls.name]) for cls in plugin_classes
    ]
    for plugin in plugins:
        log.info("plugin %s: components %s", plugin.name, sorted(plugin.enabled) or "none")
    log.info("threads: %s", thread_policy.last_decision)
    return Trainer(args, scene, plugins, model_path)


def finish_run(trainer: Trainer, result: TrainResult) -> RunSummary:
    """Evaluate the held-out views (results.json, test renders) and render the novel-time video."""
    model_path = trainer.ctx.model_path
    method = f"ours_{result.final_iteration}"
    model, background, backend = trainer.ctx.model, trainer.ctx.background, trainer.pipe.backend
    evaluation = None
    if trainer.test_cameras:
        evaluation = evaluate_cameras(model, trainer.test_cameras, "fine", background, backend,
                                      out_dir=model_path / "test" / method)
        write_metrics(model_path, method, evaluation)
        summary = ", ".join(f"{k} {v:.4f}" for k, v in evaluation.mean.items() if v is not None)
        print(f"[train] test views ({len(trainer.test_cameras)}): {summary}")
        if evaluation.lpips_unavailable:
            print(f"[train] LPIPS not reported: {evaluation.lpips_unavailable}")
    video = None
    if trainer.ctx.scene.video_cameras:
        cams = [c.to(trainer.device) for c in trainer.ctx.scene.video_cameras]
        video = render_video(model, cams, "fine", background, model_path / "video" / method / "video_rgb.mp4", backend)
        print(f"[train] novel-time video: {video}")
    print(f"[train] done in {result.wall_seconds:.1f} s, {result.num_gaussians} Gaussians, output in {model_path}")
    return RunSummary(trainer, result, evaluation, video)


def train_from_argv(argv: list[str]) -> RunSummary:
    """The whole of train.py: build, train, evaluate."""
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    trainer = build_trainer(argv)
    if trainer.run.detect_anomaly:
        torch.autograd.set_detect_anomaly(True)
    result = trainer.train()
    return finish_run(trainer, result)


def run_cli(entry: Callable[[], int]) -> None:
    """Run `entry`; input errors (bad flags, files, config keys, plugins) and a diverged training
    (non-finite loss or gradients, named) print one line, exit 2.

    Set FOURDGS_TRACEBACK=1 to see the full traceback instead.
    """
    try:
        sys.exit(entry())
    except (ValueError, FileNotFoundError, NotADirectoryError, FloatingPointError) as exc:
        if os.environ.get("FOURDGS_TRACEBACK"):
            raise
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


@dataclass
class LoadedRun:
    """A trained model directory loaded for rendering or evaluation."""

    trainer: Trainer
    args: object
    iteration: int


def require_run(path: str | os.PathLike) -> Path:
    """`path` if it is a trained model directory (a `point_cloud/iteration_N/point_cloud.ply`), else
    ValueError naming it: one line, before any loading (view.py, python -m baselines.export)."""
    from .checkpoint import PLY_FILE, find_latest_iteration, point_cloud_dir

    path = Path(path)
    if not path.is_dir():
        raise ValueError(f"{path}: no such run folder (-m/--model_path)")
    iteration = find_latest_iteration(path)
    if iteration is None or not (point_cloud_dir(path, iteration) / PLY_FILE).is_file():
        raise ValueError(f"{path} is not a trained run: no point_cloud/iteration_N/{PLY_FILE} (train.py -m {path} writes one)")
    return path


def load_run(argv: list[str]) -> LoadedRun:
    """Load `-m MODEL [--iteration N]` (render.py's flags) with its saved configuration and plugins.

    The scene is read with the saved dataset flags; plugins and component toggles are restored
    from the model directory. Raises FileNotFoundError when no saved iteration exists.
    """
    from arguments import parse_render_args, peek_plugins
    from baselines.data import load_scene

    from .checkpoint import find_latest_iteration, point_cloud_dir

    plugin_classes = [load_plugin_class(name) for name in peek_plugins(argv, from_model_dir=True)]
    extra_groups: dict[str, type] = {}
    for cls in plugin_classes:
        extra_groups.update(cls.param_groups)
    args = parse_render_args(argv, extra_groups=extra_groups)
    components = resolve_components(plugin_classes, args.run.disable, args.run.enable)
    model_path = Path(args.model.model_path)
    iteration = args.render.iteration
    if iteration < 0:
        iteration = find_latest_iteration(model_path)
        if iteration is None:
            raise FileNotFoundError(f"{model_path}: no point_cloud/iteration_N folder to render")
    pc_dir = point_cloud_dir(model_path, iteration)
    if not (pc_dir / "point_cloud.ply").is_file():
        raise FileNotFoundError(f"{pc_dir}: no point_cloud.ply (trained iterations: {find_latest_iteration(model_path)})")
    scene = load_scene(
        args.model.source_path, dataset_type=args.model.dataset_type, images=args.model.images,
        resolution=args.model.resolution, eval=args.model.eval,
        white_background=args.model.white_background, llffhold=args.model.llffhold,
    )
    plugins = [cls({g: args.extra[g] for g in cls.param_groups}, components[cls.name]) for cls in plugin_classes]
    trainer = Trainer(args, scene, plugins, model_path)
    trainer.load_model_from(pc_dir)
    return LoadedRun(trainer, args, iteration)


def render_from_argv(argv: list[str]) -> dict[str, Path]:
    """The whole of render.py: load a trained model directory and write its renders.

    Writes <model>/{train,test}/ours_<iter>/{renders,gt,depth}/, updates results.json with the
    test metrics, and renders <model>/video/ours_<iter>/video_rgb.mp4. Plugins and component
    toggles are restored from the model directory's saved configuration.
    """
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    loaded = load_run(argv)
    trainer, args, iteration = loaded.trainer, loaded.args, loaded.iteration
    model_path, scene = trainer.ctx.model_path, trainer.ctx.scene
    model, background, backend = trainer.ctx.model, trainer.ctx.background, args.pipe.backend
    method = f"ours_{iteration}"
    written: dict[str, Path] = {}
    for split, cams, skip in (("train", trainer.train_cameras, args.render.skip_train),
                              ("test", trainer.test_cameras, args.render.skip_test)):
        if skip or not cams:
            continue
        out = model_path / split / method
        result = evaluate_cameras(model, cams, "fine", background, backend, out_dir=out)
        if split == "test":
            write_metrics(model_path, method, result)
        written[split] = out
        print(f"[render] {split}: {len(cams)} views -> {out} (PSNR {result.mean['PSNR']:.3f})")
    if not args.render.skip_video and scene.video_cameras:
        cams = [c.to(trainer.device) for c in scene.video_cameras]
        written["video"] = render_video(model, cams, "fine", background,
                                        model_path / "video" / method / "video_rgb.mp4", backend)
        print(f"[render] video -> {written['video']}")
    trainer.run_log.close()
    return written
