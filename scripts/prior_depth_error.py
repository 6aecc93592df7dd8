#!/usr/bin/env python3
"""How far is the aligned monocular depth from the truth? On simulator scenes, moving vs static pixels.

    python scripts/prior_depth_error.py data/synthetic_real/truck data/synthetic_real/umbrella

For each dataset written by the simulator (it needs `gt/depth/*.npy` and `gt/motion_masks/*.png`,
which training never reads), loads the scene and the host's initial cloud as a run does (SIFT
triangulation with the known cameras, or the dataset's points), then aligns every training frame's
disparity to metric depth the way ReFlow's masks, seeds and canonical space read it: the per-frame
affine fit alone (`reflow_plugin.labels.aligned_depths`), and with the smooth correction
(`--disparity_field`, ReFlowPlugin._corrected_disparity) first. Prints one Markdown table: the
median over frames of each frame's median |depth / true depth - 1| on the truly moving pixels and
on the static ones. The moving pixels' error is what the masks' re-projection test needs small (a
moving object placed at the wrong depth can have its motion explained as parallax).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]


def frame_errors(depths: list[np.ndarray], truths: list[np.ndarray], moving: list[np.ndarray]) -> tuple[float, float]:
    """(moving, static): median over frames of the frame's median |depth / truth - 1| on those pixels."""
    per_frame = {True: [], False: []}
    for depth, truth, mask in zip(depths, truths, moving):
        error = np.abs(depth / truth - 1.0)
        for flag, pixels in ((True, mask), (False, ~mask)):
            values = error[pixels & np.isfinite(error)]
            if len(values):
                per_frame[flag].append(float(np.median(values)))
    return (float(np.median(per_frame[True])) if per_frame[True] else float("nan"),
            float(np.median(per_frame[False])) if per_frame[False] else float("nan"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", type=Path, nargs="+", help="simulator dataset folders (with gt/)")
    parser.add_argument("--configs", type=Path, default=ROOT / "arguments" / "synthetic" / "default.py")
    args = parser.parse_args(argv)
    from baselines.fourdgs.app import build_trainer
    from reflow_plugin.labels import aligned_depths
    from reflow_plugin.plugin import ReFlowPlugin, _metric_points

    print("| scene | frames | moving px, affine fit | moving px, + correction | static px, affine fit "
          "| static px, + correction | frames corrected |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for scene in args.scenes:
        for sub in ("depth", "motion_masks"):
            if not (scene / "gt" / sub).is_dir():
                raise SystemExit(f"prior_depth_error: {scene / 'gt' / sub} is missing (not a simulator dataset?)")
        with tempfile.TemporaryDirectory() as out:
            trainer = build_trainer(["-s", str(scene), "-m", out, "--configs", str(args.configs), "--quiet"])
            trainer.build()
            ctx = trainer.ctx
            cameras = ctx.train_cameras
            if any(c.disparity is None for c in cameras):
                raise SystemExit(f"prior_depth_error: {scene} has no disparity for every training view")
            truths = [np.load(scene / "gt" / "depth" / f"{c.image_name}.npy") for c in cameras]
            moving = [cv2.imread(str(scene / "gt" / "motion_masks" / f"{c.image_name}.png"), cv2.IMREAD_GRAYSCALE) > 127
                      for c in cameras]
            points = _metric_points(ctx)
            plugin = ReFlowPlugin()
            corrected = plugin._corrected_disparity(ctx)
            plain = aligned_depths(cameras, points)
            fixed = aligned_depths(corrected, points)
        if plain is None or fixed is None:
            raise SystemExit(f"prior_depth_error: {scene}: some frame has no metric fit at all")
        plain_moving, plain_static = frame_errors(plain, truths, moving)
        fixed_moving, fixed_static = frame_errors(fixed, truths, moving)
        done = (plugin.info.get("disparity_field") or {}).get("corrected", 0)
        print(f"| {scene.name} | {len(cameras)} | {plain_moving:.3f} | {fixed_moving:.3f} | {plain_static:.3f} "
              f"| {fixed_static:.3f} | {done} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
