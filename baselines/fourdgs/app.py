"""Command-line orchestration shared by train.py and render.py (and callable from tests).

`train_from_argv` turns a train.py command line into a finished run: plugins are resolved first
(they add parameter groups and flags), then flags and config files are parsed, components
toggled, the dataset loaded and checked, the model trained, the held-out views evaluated and the
novel-time video written. Every input check happens before the first training iteration; the
model folder is checked (run_folder.py) before the dataset is read, and claimed (run.json) only
once everything loaded. `run_cli` turns input errors, OS failures (a full disk, a read-only
folder) and Ctrl-C into one line each.
"""
from __future__ import annotations

import logging
import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from baselines import thread_policy
from baselines.cli_exit import flag_value as _flag_value, has_flag as _has_flag
from baselines.cli_exit import interrupted_line, resume_command, run_cli  # noqa: F401  (train.py, render.py, tests)
from baselines.machine import training_machine
from baselines.render.backends import resolve_backend
from baselines.run_folder import (FolderPlan, RunFolder, RunIdentity, TrainingInterrupted, check_run_folder,
                                  RunLock, check_saved_iteration, check_typed_model_path, default_model_path, require_run_record)

from .evaluate import EvalResult, evaluate_cameras, render_video, write_metrics
from .family_config import (dataset_family, default_config, family_background, fit_time_cells, log_decision,
                            strip_bare_defaults)
from .plugins import Plugin, load_plugin_class, resolve_components
from .trainer import Trainer, TrainResult, resolve_device

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


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


@dataclass
class ResolvedArgs:
    """A train.py command line resolved (flags, config files, plugins, components); nothing loaded."""

    args: object  # arguments.TrainArgs
    embedded: bool  # no dataset given (typed or in a config file): the embedded synthetic scene
    source: Path
    plugin_classes: list[type[Plugin]]
    components: dict[str, frozenset[str]]
    decision: object  # family_config's ConfigDecision, or None when the user chose the configs
    model_from_old_run: bool  # the model hyperparameters are --start_checkpoint's folder's (fixed shapes)


def resolve_train_args(argv: list[str]) -> ResolvedArgs:
    """Plugins, flags and config files of a train.py command line (no file but configs is read).

    Config files: `--configs` when typed; else the detected family's file (family_config.py),
    also when continuing from an output folder (`--start_checkpoint OLD[/point_cloud/iteration_N]`),
    where OLD's saved model hyperparameters go over it so that OLD's files fit the model.
    """
    from arguments import parse_train_args, peek_plugins
    from arguments.saved import model_dir_of_checkpoint

    argv, bare_defaults = strip_bare_defaults(list(argv))
    typed_source = _has_flag(argv, "-s", "--source_path")

    # Plugins first: they contribute parameter groups that the full parse must know.
    plugin_names = peek_plugins(argv)
    plugin_classes = [load_plugin_class(name) for name in plugin_names]
    decision = None
    old_run = model_dir_of_checkpoint(_flag_value(argv, "--start_checkpoint"))
    user_configs = _has_flag(argv, "--configs")
    model_from_old_run = old_run is not None and not user_configs  # OLD's model settings over the family's
    if not bare_defaults and not user_configs:
        # 4DGS's bare defaults fit no dataset: the detected family's config (family_config.py)
        source_flag = _flag_value(argv, "-s", "--source_path") or ""
        source = Path(source_flag) if typed_source else REPO_ROOT / "data" / "synthetic" / EMBEDDED_SCENE
        decision = default_config(source, plugin_names, _flag_value(argv, "--dataset_type") or "auto",
                                  family=None if typed_source else "synthetic")
        log_decision(decision)
        if decision.path is not None:
            argv += ["--configs", str(decision.path)]
    extra_groups: dict[str, type] = {}
    for cls in plugin_classes:
        extra_groups.update(cls.param_groups)
    args = parse_train_args(argv, extra_groups=extra_groups, saved_model_over_configs=model_from_old_run)
    components = resolve_components(plugin_classes, args.run.disable, args.run.enable)
    # a dataset named in a --configs file counts as given (config.json of a run names its own)
    embedded = not typed_source and not args.model.source_path
    source = REPO_ROOT / "data" / "synthetic" / EMBEDDED_SCENE if embedded else Path(args.model.source_path)
    return ResolvedArgs(args, embedded, source, plugin_classes, components, decision, model_from_old_run)


# (initial, final) learning-rate flags of one log-linear schedule (lr_schedule.get_expon_lr_func)
LR_SCHEDULES = (("position_lr_init", "position_lr_final"), ("deformation_lr_init", "deformation_lr_final"),
                ("grid_lr_init", "grid_lr_final"))


def check_schedules(opt, *, require_training: bool) -> None:
    """Schedule flags that cannot train, refused before any folder or data is touched (the
    schedules themselves would refuse them only once the initial cloud is built, and without the
    flag's name): a schedule's two rates both > 0 or both 0; with ``require_training`` (train.py),
    ``--iterations`` >= 1."""
    if require_training and opt.iterations == 0:
        raise ValueError("--iterations 0: the run would save no model (the fine stage is what render.py, "
                         "export and the viewer load); give --iterations >= 1")
    for first, last in LR_SCHEDULES:
        start, end = getattr(opt, first), getattr(opt, last)
        if (start > 0) != (end > 0):
            raise ValueError(f"--{first} {start:g} with --{last} {end:g}: a decaying rate needs both > 0 "
                             "(or both 0 to freeze the group)")


def build_trainer(argv: list[str], require_training: bool = False) -> Trainer:
    """Parse, validate and load everything a run needs; return a Trainer ready to train.

    ``require_training`` (train.py): ``--iterations 0`` is refused before anything is loaded (a
    test may build an untrained model)."""
    typed = list(argv)
    resolved = resolve_train_args(argv)
    args = resolved.args
    check_schedules(args.opt, require_training=require_training)
    seed_everything(args.opt.seed)
    # --device cuda without CUDA, --backend gsplat where it cannot run: one line before any folder or data
    resolve_backend(args.pipe.backend, resolve_device(args.pipe.device))
    folder = _check_model_folder(args, typed, resolved.source, resolved.plugin_classes,
                                 resolved.components)  # before any long work
    try:
        return _load_and_claim(args, folder, resolved.source, resolved.embedded, resolved.plugin_classes,
                               resolved.components, resolved.decision,
                               fit_cells=not resolved.model_from_old_run)
    except BaseException:
        folder.release()  # a bad input found after the lock: the folder goes back to how it was
        raise


def _load_and_claim(args, folder: RunFolder, source: Path, embedded: bool, plugin_classes: list[type[Plugin]],
                    components: dict[str, frozenset[str]], decision, fit_cells: bool = True) -> Trainer:
    """build_trainer's second half, under the folder's lock: load the dataset, commit the folder."""
    from arguments import write_cfg_args
    from baselines.data import load_scene
    from baselines.data.loader import IGNORED_ARGUMENTS
    from baselines.data.errors import EmptySplitError

    source = embedded_scene_path() if embedded else source
    args.model.source_path = str(source)
    if args.sources.get("ModelParams.white_background", "default") == "default":
        family = "synthetic" if embedded else dataset_family(source, args.model.dataset_type)
        white = family_background(family)
        if white is not None:
            args.model.white_background = white
            args.sources["ModelParams.white_background"] = f"{family} family"
            log.info("background: %s (%s family; -w / --no-white_background to choose)",
                     "white" if white else "black", family)
    plugins: list[Plugin] = [
        cls({g: args.extra[g] for g in cls.param_groups}, components[cls.name]) for cls in plugin_classes
    ]
    try:
        scene = load_scene(
            source, dataset_type=args.model.dataset_type, images=args.model.images,
            resolution=args.model.resolution, eval=args.model.eval,
            white_background=args.model.white_background, llffhold=args.model.llffhold,
            reader_options=reader_options(source, args.model),
        )
    except EmptySplitError as err:
        raise EmptySplitError(f"{err}{_frame_needs(plugins, 0, prefix='; ')}") from None
    if len(scene.train_cameras) < max([1] + [p.min_train_frames()[0] for p in plugins]):
        honours_eval = "eval" not in IGNORED_ARGUMENTS.get(scene.dataset_type, ())  # HyperNeRF: fixed split
        held = (f"; --no-eval trains on the {len(scene.test_cameras)} held-out frame(s) too"
                if scene.test_cameras and honours_eval else "")
        raise ValueError(f"{source}: {len(scene.train_cameras)} training frame(s)"
                         f"{_frame_needs(plugins, len(scene.train_cameras))}{held}")
    if decision is not None and decision.path is not None and fit_cells:  # not an old run's fixed grid
        _fit_time_cells(args, scene)
    model_path = folder.path
    folder.commit()
    try:
        write_cfg_args(model_path, args, {"_components": {name: sorted(active) for name, active in components.items()},
                                           "_dataset_layout": scene.metadata.get("layout_detection"),
                                           "_protocol": scene.metadata.get("protocol"),
                                           "_default_config": decision.as_dict() if decision else None})
        for plugin in plugins:
            log.info("plugin %s: components %s", plugin.name, sorted(plugin.enabled) or "none")
        log.info("threads: %s", thread_policy.last_decision)
        trainer = Trainer(args, scene, plugins, model_path)  # e.g. --device cuda without CUDA fails here
        machine = training_machine(trainer.device, args.pipe.backend, args.hidden.mlp_precision)
        log.info("machine: %s", ", ".join(f"{k} {v}" for k, v in machine.items()))
        folder.record_facts(machine=machine)  # mlp_arithmetic differs between CPUs under "auto"
    except BaseException:
        folder.abandon()  # nothing trained yet: the folder goes back to how it was
        raise
    trainer.run_folder = folder
    return trainer


def _fit_time_cells(args, scene) -> None:
    """The family config's temporal HexPlane resolution fitted to the capture's frame count
    (family_config.fit_time_cells), unless the command line set ``--kplanes_config``."""
    key = "ModelHiddenParams.kplanes_config"
    resolution = list(args.hidden.kplanes_config.get("resolution", []))
    if args.sources.get(key) == "command line" or len(resolution) != 4:
        return
    times = {round(float(c.time), 9) for c in (*scene.train_cameras, *scene.test_cameras)}
    cells = fit_time_cells(resolution[3], len(times))
    if cells == resolution[3]:
        return
    log.info("HexPlane time cells: %d (half of the capture's %d frame times; with the config's %d, cells between "
             "the training frames' times get no gradient; --kplanes_config sets them)", cells, len(times), resolution[3])
    args.hidden.kplanes_config = {**args.hidden.kplanes_config, "resolution": [*resolution[:3], cells]}
    args.sources[key] = f"{args.sources.get(key, 'default')}, time cells fitted to {len(times)} frames"


# ModelParams fields only the panoptic reader reads, with the flag that sets each
PANOPTIC_ONLY = (("train_cameras", "--train_cameras"), ("test_cameras", "--test_cameras"), ("test_every", "--test_every"))


def reader_options(source: Path | str, model) -> dict:
    """The chosen reader's own options from ``ModelParams`` (panoptic: its camera cycle and test stride).

    Raises:
        ValueError: a panoptic-only option set away from its default for a dataset of another
            family (it would be dropped without a word; the split it asks for would not happen).
    """
    from arguments.params import ModelParams

    family = dataset_family(Path(source), model.dataset_type)
    if family != "panoptic":
        defaults = ModelParams()
        changed = [flag for name, flag in PANOPTIC_ONLY if getattr(model, name) != getattr(defaults, name)]
        if changed:
            raise ValueError(f"{', '.join(changed)}: read by the panoptic reader only, and {source} is a {family} "
                             "dataset; its split is set with --eval / --llffhold")
        return {}
    return {"train_cameras": model.train_cameras or None, "test_cameras": model.test_cameras or None,
            "test_every": model.test_every}


def _check_model_folder(args, argv: list[str], source: Path, plugin_classes: list[type[Plugin]],
                        components: dict[str, frozenset[str]]) -> RunFolder:
    """Where the run goes and whether that folder may take it (run_folder.py); nothing is written."""
    start = args.run.start_checkpoint
    check_typed_model_path(_flag_value(argv, "-m", "--model_path"))
    if args.model.model_path:
        model_path = Path(args.model.model_path)
    elif start and Path(start).is_file() and (Path(start).parent / "run.json").is_file():
        model_path = Path(start).parent  # continuing a chkpnt of a run folder: that folder
    elif args.run.expname:
        model_path = REPO_ROOT / "output" / args.run.expname
    else:
        model_path = default_model_path(REPO_ROOT / "output" / source.name)
    args.model.model_path = str(model_path)
    identity = RunIdentity.of([c.name for c in plugin_classes], components, str(source))
    outputs = [name for cls in plugin_classes for name in getattr(cls, "outputs", ())]
    for name in _recorded_plugins(model_path):
        try:
            outputs += list(getattr(load_plugin_class(name), "outputs", ()))
        except ValueError:
            pass  # a plugin not installed now: its files are kept
    def check() -> FolderPlan:
        return check_run_folder(model_path, identity, overwrite=args.run.overwrite, start_checkpoint=start,
                                plugin_outputs=outputs)

    folder = RunFolder(check(), identity, ["train.py", *argv])
    folder.claim(check)  # the lock, then the same check again: no other run slips in between
    return folder


def _frame_needs(plugins: list[Plugin], have: int, prefix: str = ": ") -> str:
    """What the plugins need in training frames beyond `have` (one clause per plugin), or ''."""
    parts = []
    for plugin in plugins:
        count, what = plugin.min_train_frames()
        if count > max(have, 1) or (have == 0 and count > 1):
            names = ",".join(c.strip() for c in what.split(",") if c.strip())
            parts.append(f"--plugin {plugin.name} needs at least {count} training frames for {what} "
                         f"(more frames, or --disable {names})")
    return prefix + "; ".join(parts) if parts else ""


def _recorded_plugins(model_path: Path) -> list[str]:
    from arguments.saved import read_saved_plugins

    try:
        return read_saved_plugins(model_path) if model_path.is_dir() else []
    except ValueError:
        return []


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
    trainer = build_trainer(argv, require_training=True)
    if trainer.run.detect_anomaly:
        torch.autograd.set_detect_anomaly(True)
    folder = trainer.run_folder
    try:
        return _train_locked(trainer, folder, argv)
    finally:
        folder.release()  # the run is over (finished, failed or interrupted): the folder is free


def _train_locked(trainer: Trainer, folder: RunFolder, argv: list[str]) -> RunSummary:
    try:
        summary = finish_run(trainer, trainer.train())
    except TrainingInterrupted as stop:
        folder.end("interrupted", stopped_at=f"{stop.stage} iteration {stop.iteration}",
                   last_checkpoint=str(stop.checkpoint), resume=resume_command(argv, folder.path, stop.checkpoint))
        raise
    except BaseException as exc:
        if trainer.ctx.iteration == 0 and folder.writes == 0:
            folder.abandon()  # a bad input found before the first iteration: leave the folder as it was
        else:
            state = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
            folder.end(state, reason=f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}",
                       stopped_at=f"{trainer.ctx.stage} iteration {trainer.ctx.iteration}")
        raise
    finally:
        trainer.run_log.close()
    folder.end("finished", stopped_at=f"{trainer.ctx.stage} iteration {trainer.ctx.iteration}")
    return summary


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
    require_run_record(path)  # an unreadable run.json: no "latest" iteration can be trusted
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

    from .checkpoint import FolderContentError, find_latest_iteration, point_cloud_dir

    plugin_classes = [load_plugin_class(name) for name in peek_plugins(argv, from_model_dir=True)]
    extra_groups: dict[str, type] = {}
    for cls in plugin_classes:
        extra_groups.update(cls.param_groups)
    args = parse_render_args(argv, extra_groups=extra_groups)
    components = resolve_components(plugin_classes, args.run.disable, args.run.enable)
    model_path = Path(args.model.model_path)
    require_run_record(model_path)  # an unreadable run.json: which folders the run saved is unknown
    iteration = args.render.iteration
    if iteration < 0:
        iteration = find_latest_iteration(model_path)
        if iteration is None:
            raise FileNotFoundError(f"{model_path}: no point_cloud/iteration_N folder to render")
    pc_dir = point_cloud_dir(model_path, iteration)
    if not (pc_dir / "point_cloud.ply").is_file():
        raise FileNotFoundError(f"{pc_dir}: no point_cloud.ply (trained iterations: {find_latest_iteration(model_path)})")
    check_saved_iteration(model_path, pc_dir)  # never metrics of another run's leftover folder
    scene = load_scene(
        args.model.source_path, dataset_type=args.model.dataset_type, images=args.model.images,
        resolution=args.model.resolution, eval=args.model.eval,
        white_background=args.model.white_background, llffhold=args.model.llffhold,
        reader_options=reader_options(args.model.source_path, args.model),
    )
    plugins = [cls({g: args.extra[g] for g in cls.param_groups}, components[cls.name]) for cls in plugin_classes]
    trainer = Trainer(args, scene, plugins, model_path)
    trainer.run_log.quiet = args.render.quiet  # this command's --quiet, not the training run's saved one
    try:
        trainer.load_model_from(pc_dir)
    except FolderContentError:
        raise  # a missing or damaged file: no flag fixes that
    except ValueError as err:
        if not args.shape_overrides:
            raise
        raise ValueError(f"{err}; given here: {', '.join(args.shape_overrides)}: a trained model's "
                         f"shape comes from its run ({model_path}), leave these flags out") from None
    return LoadedRun(trainer, args, iteration)


def render_from_argv(argv: list[str]) -> dict[str, Path]:
    """The whole of render.py: load a trained model directory and write its renders.

    Writes <model>/{train,test}/ours_<iter>/{renders,gt,depth}/, updates results.json with the
    test metrics, and renders <model>/video/ours_<iter>/video_rgb.mp4. Plugins and component
    toggles are restored from the model directory's saved configuration.
    """
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    root = logging.getLogger()
    level = root.level
    if _has_flag(argv, "--quiet"):  # this command's own flag, not the training run's saved `quiet`
        root.setLevel(logging.WARNING)  # warnings and the written folders only
    try:
        loaded = load_run(argv)
        lock = RunLock(loaded.trainer.ctx.model_path).acquire()  # no training or other render writes here meanwhile
        try:
            return _render_locked(loaded)
        finally:
            loaded.trainer.run_log.close()
            lock.release()
    finally:
        root.setLevel(level)


def _render_locked(loaded: LoadedRun) -> dict[str, Path]:
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
    return written
