"""Synthetic check of `python -m baselines.prepare`: render a hand-held-like clip with known
cameras, write it as an .mp4, prepare it (masks auto and none) and compare the recovered cameras
with the truth up to a similarity transform.

    OMP_NUM_THREADS=1 python benchmarks/prepare_synthetic.py [--frames 24 --width 160 --out output/prepare_bench]

The scene is the simulator's static room with an orbiting camera plus a large textured box
crossing the view (a moving object that SfM must ignore). Helpers are shared with
tests/test_prepare.py.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from baselines.prepare.evaluate import compare_with_truth  # noqa: E402
from baselines.synthetic import (Orbit, Pan, RigidMotion, SceneObject, SceneSpec, StaticCamera, Texture,  # noqa: E402
                                 get_scene, simulate)


def video_scene(frames: int = 24, width: int = 160, height: int = 120, sweep_deg: float = 30.0,
                camera: str = "orbit", mover_size: float = 0.3, mover_speed: float = 1.0) -> SceneSpec:
    """The static room, a camera and a big box moving across the view (diagonally: motion along
    the horizontal epipolar lines of an orbit is invisible to masks). `camera`: "orbit" (moves
    on an arc, looking at the room), "static" (never moves) or "pan" (turns on the spot).
    `mover_speed` scales the box's velocity and spin (slower: its matches survive verification)."""
    room = get_scene("static")
    mover = SceneObject("mover", "box", size=(mover_size,) * 3, position=(-1.2, 1.0, -0.4),
                        texture=Texture("checker", ((0.95, 0.9, 0.2), (0.1, 0.3, 0.8)), period=0.1, detail=0.3),
                        motion=RigidMotion(velocity=tuple(mover_speed * v for v in (1.6, 0.9, 0.6)),
                                           spin_deg=90.0 * mover_speed))
    paths = {"orbit": Orbit(target=(0.0, 1.0, -1.0), radius=4.0, height=0.4, start_deg=-sweep_deg / 2,
                            sweep_deg=sweep_deg),
             "static": StaticCamera(position=(0.0, 1.4, 3.0), look_at=(0.0, 1.0, -1.0)),
             "pan": Pan(position=(0.0, 1.4, 3.0), look_at=(0.0, 1.0, -1.0), sweep_deg=sweep_deg)}
    return dataclasses.replace(room, name="prepare_clip", objects=room.objects + (mover,), camera=paths[camera],
                               frames=frames, width=width, height=height,
                               description="orbiting camera, one large moving box (prepare benchmark)")


def write_video(scene_dir: Path, video: Path, fps: float = 24.0) -> Path:
    """The scene's images/ as an .mp4 (mp4v codec) at `fps`."""
    files = sorted((scene_dir / "images").glob("*.png"))
    first = cv2.imread(str(files[0]))
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), fps, (first.shape[1], first.shape[0]))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write {video}")
    for path in files:
        writer.write(cv2.imread(str(path)))
    writer.release()
    return video


def render_clip(out: Path, **scene_options) -> tuple[Path, Path]:
    """(scene folder with ground truth, .mp4) of `video_scene(**scene_options)` under `out`."""
    scene_dir = simulate(video_scene(**scene_options), out / "scene", progress=False)
    return scene_dir, write_video(scene_dir, out / "clip.mp4")


def run_prepare(video: Path, dataset: Path, *extra: str) -> subprocess.CompletedProcess:
    """`python -m baselines.prepare VIDEO -o DATASET ...` in a subprocess."""
    return subprocess.run([sys.executable, "-m", "baselines.prepare", str(video), "-o", str(dataset), *extra],
                          cwd=REPO, capture_output=True, text=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--mover-size", type=float, default=0.3, help="half extent of the moving box (scene units)")
    parser.add_argument("--mover-speed", type=float, default=1.0, help="scale of the box's velocity and spin")
    parser.add_argument("--out", type=Path, default=REPO / "output" / "prepare_bench")
    args = parser.parse_args()
    scene_dir, video = render_clip(args.out, frames=args.frames, width=args.width, height=args.width * 3 // 4,
                                   mover_size=args.mover_size, mover_speed=args.mover_speed)
    moving = np.mean([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).mean() / 255 for p in (scene_dir / "motion_masks").glob("*.png")])
    print(f"clip: {args.frames} frames {args.width}x{args.width * 3 // 4}, moving box covers {moving:.1%} of the view on average")
    truth = json.loads((scene_dir / "gt" / "cameras.json").read_text())["frames"]
    true_focal = truth[0]["K"][0][0]
    print("| masks | registered | mean reprojection error (px) | points | rotation error (deg, max) "
          "| relative rotation error (deg, max) | position error (% of extent, max) | focal error | prepare wall s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for masks in ("auto", "none"):
        dataset = args.out / f"dataset_{masks}"
        start = time.perf_counter()
        result = run_prepare(video, dataset, "--masks", masks, "--quiet")
        wall = time.perf_counter() - start
        if result.returncode != 0:
            print(f"| {masks} | failed: {result.stderr.strip().splitlines()[-1]} |")
            continue
        report = json.loads((dataset / "prepare_report.json").read_text())
        errors = compare_with_truth(dataset, truth)
        print(f"| {masks} | {report['registered_frames']}/{report['extracted_frames']} "
              f"| {report['mean_reprojection_error_px']:.3f} | {report['points']} "
              f"| {errors['rotation_error_deg_max']:.3f} | {errors['relative_rotation_error_deg_max']:.3f} "
              f"| {100 * errors['position_error_rel_max']:.2f} "
              f"| {100 * (report['camera']['params'][0] / true_focal - 1):+.1f}% | {wall:.1f} |")


if __name__ == "__main__":
    main()
