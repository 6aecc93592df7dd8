"""Exported 3D tracks against the simulator's ground-truth flow, for several runs of one scene.

    python benchmarks/track_epe.py output/skating_base output/skating_reflow [--out output/tracks_bench]

For each run: the tracks `python -m baselines.export --format tracks` writes (the dynamic
Gaussians; a 4DGS baseline deforms every Gaussian, so all of its Gaussians), at every camera's
time, scored by `baselines.export.track_eval` on the held-out (test) and training views: tracks
inside the motion mask whose depth agrees with the ground-truth surface (so the same region for
every run), end-point error of their projected motion f -> f + 1 against `gt/flow_fwd`. The
zero-motion column is the error of the same tracks held still (camera motion only). Prints a
markdown table; with --out the npz files are kept.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()

from baselines.export.track_eval import track_flow_errors  # noqa: E402
from baselines.export.tracks import compute_tracks, dynamic_rows, save_tracks  # noqa: E402
from baselines.fourdgs.app import load_run, require_run  # noqa: E402


def fmt(value: float | None, digits: int = 3) -> str:
    return "" if value is None else f"{value:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--out", type=Path, default=None, help="keep each run's tracks.npz under OUT/<run name>/")
    parser.add_argument("--depth_tolerance", type=float, default=0.05)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    print("| run | tracks exported | split | pairs | track samples (distinct tracks) | median EPE px | mean EPE px | "
          "zero-motion median px | export s |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for path in args.runs:
        require_run(path)
        loaded = load_run(["-m", path])
        trainer = loaded.trainer
        model = trainer.ctx.model
        start = time.perf_counter()
        cameras = [*trainer.train_cameras, *trainer.test_cameras]
        tracks = compute_tracks(model, sorted({float(c.time) for c in cameras}), dynamic_rows(model))
        tracks.set_views(trainer.train_cameras, trainer.test_cameras)
        seconds = time.perf_counter() - start
        if args.out is not None:
            save_tracks(args.out / Path(path).name / "tracks.npz", tracks)
        for split in ("test", "train"):
            result = track_flow_errors(tracks, trainer.ctx.scene.source_path, split, "dynamic", args.depth_tolerance)
            if not result["available"]:
                print(f"| {Path(path).name} | {tracks.num_tracks} | {split} | not available: {result['reason']} |")
                continue
            print(f"| {Path(path).name} | {tracks.num_tracks} | {split} | {len(result['pairs'])} | "
                  f"{result['tracks']} ({result['distinct_tracks']}) | {fmt(result['median_epe'])} | "
                  f"{fmt(result['mean_epe'])} | {fmt(result['median_zero_motion'])} | {seconds:.1f} |")
        trainer.run_log.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
