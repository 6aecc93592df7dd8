#!/usr/bin/env python3
"""Train the 4DGS baseline, optionally with plugins (ReFlow), on a dataset or the embedded scene.

    python train.py -s data/nvidia/Skating --plugin reflow
    python train.py -s data/nvidia/Skating                      # the 4DGS baseline, same loop
    python train.py -s ... --plugin reflow --disable full_flow,cam_flow
    python train.py -s ... --start_checkpoint output/old4dgs/point_cloud/iteration_14000
    python train.py                                             # no data: embedded synthetic scene

Every input is checked (flags, config files, plugins, components, dataset files) before the first
training iteration. The run ends with an evaluation of the held-out views (results.json), test
renders and a novel-time video in the 4DGS output layout.
"""
from __future__ import annotations

import logging
import random
import sys
from pathlib import Path

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parent
EMBEDDED_SCENE = "balloon"
EMBEDDED_CONFIG = REPO_ROOT / "arguments" / "synthetic" / "default.py"


def embedded_scene_path() -> Path:
    """Generate the embedded synthetic scene once (data/synthetic/<name>) and return its path."""
    from baselines.synthetic import get_scene, simulate

    path = REPO_ROOT / "data" / "synthetic" / EMBEDDED_SCENE
    if not (path / "poses_bounds.npy").is_file():
        print(f"[train] generating the embedded synthetic scene {EMBEDDED_SCENE!r} into {path}")
        simulate(get_scene(EMBEDDED_SCENE), path)
    return path


def _has_flag(argv: list[str], *names: str) -> bool:
    return any(a == n or a.startswith(n + "=") for a in argv for n in names)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def main(argv: list[str] | None = None) -> int:
    from arguments import parse_train_args, peek_plugins, write_cfg_args
    from baselines.data import load_scene
    from baselines.fourdgs.evaluate import evaluate_cameras, render_video, write_metrics
    from baselines.fourdgs.plugins import load_plugin_class, resolve_components
    from baselines.fourdgs.trainer import Trainer

    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    argv = list(sys.argv[1:] if argv is None else argv)
    embedded = not _has_flag(argv, "-s", "--source_path")
    if embedded and not _has_flag(argv, "--configs"):
        argv += ["--configs", str(EMBEDDED_CONFIG)]

    # Plugins first: they contribute parameter groups that the full parse must know.
    plugin_classes = [load_plugin_class(name) for name in peek_plugins(argv)]
    extra_groups: dict[str, type] = {}
    for cls in plugin_classes:
        extra_groups.update(cls.param_groups)
    args = parse_train_args(argv, extra_groups=extra_groups)
    components = resolve_components(plugin_classes, args.run.disable, args.run.enable)
    seed_everything(args.opt.seed)

    source = embedded_scene_path() if embedded else Path(args.model.source_path)
    args.model.source_path = str(source)
    scene = load_scene(
        source, dataset_type=args.model.dataset_type, images=args.model.images,
        resolution=args.model.resolution, eval=args.model.eval,
        white_background=args.model.white_background, llffhold=args.model.llffhold,
    )
    name = args.run.expname or source.name
    model_path = Path(args.model.model_path or REPO_ROOT / "output" / name)
    args.model.model_path = str(model_path)
    model_path.mkdir(parents=True, exist_ok=True)
    write_cfg_args(model_path, args)

    plugins = [
        cls({g: args.extra[g] for g in cls.param_groups}, components[cls.name]) for cls in plugin_classes
    ]
    trainer = Trainer(args, scene, plugins, model_path)
    if args.run.detect_anomaly:
        torch.autograd.set_detect_anomaly(True)
    result = trainer.train()

    method = f"ours_{result.final_iteration}"
    model, background, backend = trainer.ctx.model, trainer.ctx.background, args.pipe.backend
    if trainer.test_cameras:
        evaluation = evaluate_cameras(model, trainer.test_cameras, "fine", background, backend,
                                      out_dir=model_path / "test" / method)
        write_metrics(model_path, method, evaluation)
        summary = ", ".join(f"{k} {v:.4f}" for k, v in evaluation.mean.items() if v is not None)
        print(f"[train] test views ({len(trainer.test_cameras)}): {summary}")
        if evaluation.lpips_unavailable:
            print(f"[train] LPIPS not reported: {evaluation.lpips_unavailable}")
    if scene.video_cameras:
        video_cams = [c.to(trainer.device) for c in scene.video_cameras]
        path = render_video(model, video_cams, "fine", background, model_path / "video" / method / "video_rgb.mp4", backend)
        print(f"[train] novel-time video: {path}")
    print(f"[train] done in {result.wall_seconds:.1f} s, {result.num_gaussians} Gaussians, output in {model_path}")
    return 0


def run_cli(entry) -> None:
    """Run `entry`; input errors (bad flags, files, config keys, plugins) print one line and exit 2.

    Set FOURDGS_TRACEBACK=1 to see the full traceback instead.
    """
    import os

    try:
        sys.exit(entry())
    except (ValueError, FileNotFoundError, NotADirectoryError) as exc:
        if os.environ.get("FOURDGS_TRACEBACK"):
            raise
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    run_cli(main)
