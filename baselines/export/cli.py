"""`python -m baselines.export`: a trained run's deformed Gaussians as standard files.

    python -m baselines.export -m RUN --times 0 0.5 1 --format ply -o OUT
        OUT/point_cloud_t0.0000.ply ...  one Inria 3DGS PLY per time (x y z, nx ny nz, f_dc_*,
                                         f_rest_*, opacity, scale_*, rot_*), the model deformed to
                                         that time: SuperSplat and other 3DGS viewers open it
    python -m baselines.export -m RUN --format tracks -o OUT [--times ...] [--all_gaussians]
        OUT/tracks.npz                   the dynamic Gaussians' centres over time + visibility
                                         (baselines/export/tracks.py), at every frame time of the
                                         run's cameras unless --times is given
        OUT/tracks_test.mp4              their 2D trails over the rendered test views
                                         (--video_views all: every camera; --no_video: none)

Render flags of render.py (`--iteration N`, `--backend`, ...) are accepted. Bad input gives one
`error:` line and exit code 2 before anything is loaded where possible: a folder that is not a
trained run, times that are not finite or outside [0, 1], `--format ply` without `--times`, and
tracks asked of a run with no dynamic Gaussian (its deformation table is all False; the
baseline 4DGS deforms every Gaussian, so all of them are its tracks).
"""
from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import torch

from baselines.fourdgs.app import load_run, require_run
from baselines.fourdgs.checkpoint import atomic_write_ply, state_to_ply

from .tracks import compute_tracks, dynamic_rows, save_tracks
from .track_video import write_track_video

log = logging.getLogger("export")


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    parser = argparse.ArgumentParser(prog="python -m baselines.export", description=__doc__.split("\n\n")[0])
    parser.add_argument("-m", "--model_path", required=True, help="trained run folder (train.py's -m)")
    parser.add_argument("--format", required=True, choices=("ply", "tracks"))
    parser.add_argument("-o", "--out", required=True, type=Path, help="output folder")
    parser.add_argument("--times", type=float, nargs="+", help="times in [0, 1] (tracks: default every camera's time)")
    parser.add_argument("--all_gaussians", action="store_true", help="tracks: every Gaussian, not only the dynamic ones")
    parser.add_argument("--no_video", action="store_true", help="tracks: no MP4")
    parser.add_argument("--video_views", default="test", choices=("test", "all"), help="tracks: cameras of the MP4")
    parser.add_argument("--max_tracks", type=int, default=400, help="tracks drawn in the MP4 (default 400)")
    parser.add_argument("--trail", type=float, default=0.3, help="trail length in normalised time (default 0.3)")
    parser.add_argument("--fps", type=int, default=5, help="tracks: frame rate of the MP4 (default 5)")
    args, rest = parser.parse_known_args(argv)
    if args.times is not None:
        bad = [t for t in args.times if not (math.isfinite(t) and 0.0 <= t <= 1.0)]
        if bad:
            raise ValueError(f"--times must be finite and in [0, 1], got {bad}")
    if args.format == "ply" and not args.times:
        raise ValueError("--format ply needs --times (e.g. --times 0 0.5 1)")
    for flag, value in (("--max_tracks", args.max_tracks), ("--fps", args.fps)):
        if value < 1:
            raise ValueError(f"{flag} {value}: must be >= 1")
    if not args.trail >= 0:  # NaN too
        raise ValueError(f"--trail {args.trail}: must be >= 0")
    return args, ["-m", args.model_path, *rest]


def export_ply(model, times: list[float], out: Path) -> list[Path]:
    """One PLY per time: the model deformed to that time (fine stage)."""
    written = []
    with torch.no_grad():
        for t in times:
            path = atomic_write_ply(state_to_ply(model.deform(float(t), "fine")), out / f"point_cloud_t{t:.4f}.ply")
            written.append(path)
            print(f"[export] t={t:.4f}: {model.num_gaussians} Gaussians -> {path}")
    return written


def export_tracks(loaded, args: argparse.Namespace) -> list[Path]:
    """tracks.npz (+ the MP4) of the dynamic Gaussians, or of all with --all_gaussians."""
    trainer = loaded.trainer
    model = trainer.ctx.model
    rows = None if args.all_gaussians else dynamic_rows(model)
    if rows is not None and rows.numel() == 0:
        raise ValueError(f"{args.model_path}: the run has no dynamic part (its deformation table is all False, "
                         "so nothing moves); --all_gaussians exports every Gaussian's (constant) track")
    cameras = [*trainer.train_cameras, *trainer.test_cameras]
    times = sorted(set(args.times)) if args.times else sorted({float(c.time) for c in cameras})
    tracks = compute_tracks(model, times, rows)
    tracks.set_views(trainer.train_cameras, trainer.test_cameras)
    written = [save_tracks(args.out / "tracks.npz", tracks)]
    if args.all_gaussians:
        what = "every Gaussian"
    elif tracks.num_tracks == model.num_gaussians:
        what = "every Gaussian: the run deforms all of them, as 4DGS does"
    else:
        what = f"the dynamic Gaussians, of {model.num_gaussians}"
    print(f"[export] {tracks.num_tracks} tracks ({what}) x {len(times)} times -> {written[0]}")
    if args.no_video:
        return written
    views = trainer.test_cameras if args.video_views == "test" else cameras
    known = [c for c in views if any(abs(c.time - t) <= 1e-5 for t in times)]
    if len(known) < len(views):
        log.warning("%d of %d %s views have a time that is not among --times: not in the video",
                    len(views) - len(known), len(views), args.video_views)
    if not known:
        print(f"[export] no video: no {args.video_views} view at one of the exported times")
        return written
    path = write_track_video(model, tracks, [c.to(trainer.device) for c in known], trainer.ctx.background,
                             args.out / f"tracks_{args.video_views}.mp4", trail=args.trail, max_tracks=args.max_tracks,
                             fps=args.fps, backend=loaded.args.pipe.backend)
    print(f"[export] trails over {len(known)} {args.video_views} views -> {path}")
    return written + [path]


def check_export_folder(out: Path) -> None:
    """`-o` must be a folder (or not exist yet) and not inside a run's point_cloud/ folder, where the
    written files would mix with a saved iteration (and break its manifest)."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"-o {out}: is a file, not a folder; choose another -o")
    resolved = out.resolve()
    for folder in (resolved, *resolved.parents):
        if folder.name == "point_cloud" and (folder.parent / "run.json").is_file():
            raise ValueError(f"-o {out}: inside the run folder {folder.parent}'s point_cloud/ (its saved "
                             "iterations); choose a folder outside it")


def main(argv: list[str] | None = None) -> int:
    args, run_argv = parse_args(list(sys.argv[1:] if argv is None else argv))
    require_run(args.model_path)
    check_export_folder(args.out)  # before the model loads
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    loaded = load_run(run_argv)
    try:
        if args.format == "ply":
            export_ply(loaded.trainer.ctx.model, args.times, args.out)
        else:
            export_tracks(loaded, args)
    finally:
        loaded.trainer.run_log.close()
    return 0
