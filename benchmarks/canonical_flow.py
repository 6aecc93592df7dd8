"""The flow provider's canonical static cloud on real sequences: its depth error against the SfM points.

    OMP_NUM_THREADS=1 python benchmarks/canonical_flow.py --data data/real [--captures davis_dog,davis_libby]
        [--downscale 2] [--spreads 1 4] [--finest preset 0] [--align off|on|both]

For each DAVIS-style capture (a camera path without disparity, so ReFlow's canonical space comes
from DIS optical flow triangulated with the dataset's cameras) at the benchmark's size times
1/--downscale, builds the canonical space with the dataset's motion masks (what a ReFlow run
uses): first ReFlow's default (spread 1, DIS's preset, alignment on), then every variant of the
flow provider's partner spread (1 = frames n +- 1; k > 1 = every frame within k, fused:
`FlowProvider.fused_depth`; A/B switch REFLOW4DGS_FLOW_SPREAD) x DIS's finest pyramid level
(`preset` = 1, half resolution; 0 = full; switch REFLOW4DGS_FLOW_FINEST) x the pairwise alignment
(`--canonical_align`). Prints one table: the static cloud's median relative depth error per 4-px
cell against the sparse points (`canonical.check.depth_error_to_anchors`, the figure ReFlow's
initial-cloud check compares with its 2% limit, FLOW_CLOUD_MAX_DEPTH_ERROR), the 10th / 50th /
90th percentile of the depth ratio, the static points and the seconds. No training: this says
whether the canonical space would pass its check, not what it does to PSNR.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from real_captures import CAPTURES, CaptureError, dataset_dir, select  # noqa: E402  (benchmarks/ is on sys.path above)


def measure(scene, spread: int, align: bool, finest: int | None = None) -> dict:
    """One variant's canonical static cloud against the scene's sparse points (finest: DIS's finest
    pyramid level, None = the preset's)."""
    from reflow_plugin.canonical import build_canonical_space, options_from_params
    from reflow_plugin.canonical.check import cell_ratios
    from reflow_plugin.params import ReFlowParams

    cameras = scene.train_cameras
    masks = [c.mask.detach().cpu().numpy().reshape(c.height, c.width) > 0.5 for c in cameras]
    anchors = np.asarray(scene.point_cloud.points, np.float64)
    options = replace(options_from_params(ReFlowParams()), cache=False, align=align, flow_spread=spread,
                      flow_finest_scale=finest, provider="flow")
    start = time.perf_counter()
    space = build_canonical_space(scene, masks, options, progress=False, anchors=anchors)
    seconds = time.perf_counter() - start
    _, ratios = cell_ratios(np.asarray(space.static.points), anchors, cameras)
    row = {"spread": spread, "finest": "preset" if finest is None else finest, "align": align,
           "static": len(space.static), "seconds": seconds, "cells": len(ratios)}
    if len(ratios):
        row["error"] = float(np.median(np.abs(ratios - 1)))
        row["ratio"] = [float(v) for v in np.percentile(ratios, [10, 50, 90])]
    return row


def usable(scene) -> str | None:
    """Why the capture is not measured here (None: it is a flow-provider sequence with masks and points)."""
    from reflow_plugin.rig import wide_rig

    cameras = sorted(scene.train_cameras, key=lambda c: (c.time, c.frame_index))
    if all(c.disparity is not None for c in cameras):
        return "has disparity: ReFlow uses the depth provider"
    if any(c.mask is None for c in cameras):
        return "training views without motion masks"
    if scene.point_cloud is None or len(scene.point_cloud.points) == 0:
        return "no sparse points to compare with"
    if wide_rig([c.viewmat.double().cpu().numpy() for c in cameras]):
        return "a wide rig: partners by camera, not by time"
    return None


def table(rows: list[dict]) -> str:
    lines = ["| capture | spread | DIS finest | align | depth error % | ratio p10 / p50 / p90 | static points | s |",
             "|---|---:|---|---|---:|---|---:|---:|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['capture']} | - | - | - | skipped: {r['skipped']} | | | |")
            continue
        error = f"{100 * r['error']:.1f}" if "error" in r else "no cell"
        ratio = " / ".join(f"{v:.3f}" for v in r["ratio"]) if "ratio" in r else "-"
        lines.append(f"| {r['capture']} | {r['spread']} | {r['finest']} | {'on' if r['align'] else 'off'} | {error} | "
                     f"{ratio} | {r['static']:,} | {r['seconds']:.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data" / "real")
    parser.add_argument("--captures", help="comma-separated names (default: every davis_* capture)")
    parser.add_argument("--downscale", type=int, default=2, help="-r = the capture's resolution x this (default 2: "
                                                                 "the budget-3000 benchmark's size)")
    parser.add_argument("--spreads", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--finest", nargs="+", default=["preset", "0"],
                        help="DIS finest levels: preset (1) or integers >= 0")
    parser.add_argument("--align", choices=("both", "on", "off"), default="off",
                        help="alignment of the variants (ReFlow's default row is always measured aligned)")
    args = parser.parse_args(argv)
    if any(s < 1 for s in args.spreads):
        parser.error("--spreads: every value must be >= 1")
    if any(f != "preset" and not f.isdigit() for f in args.finest):
        parser.error("--finest: each value is 'preset' or an integer >= 0")
    finest = [None if f == "preset" else int(f) for f in args.finest]
    from baselines.data.errors import DatasetError
    from baselines.data.loader import load_scene

    try:
        captures = select(args.captures) if args.captures else [c for n, c in CAPTURES.items()
                                                                 if n.startswith("davis_")]
    except CaptureError as err:
        parser.error(str(err))
    aligns = {"both": (True, False), "on": (True,), "off": (False,)}[args.align]
    rows = []
    for capture in captures:
        folder = dataset_dir(capture, args.data)
        if not folder.is_dir():
            rows.append({"capture": capture.name, "skipped": f"{folder} not set up"})
            continue
        try:
            scene = load_scene(folder, resolution=capture.resolution * args.downscale, eval=True)
        except DatasetError as err:  # e.g. a clip prepare refused (a static camera): no dataset in the folder
            rows.append({"capture": capture.name, "skipped": str(err).split(";")[0]})
            continue
        why = usable(scene)
        if why:
            rows.append({"capture": capture.name, "skipped": why})
            continue
        variants = [(1, None, True)] + [(s, f, a) for s in args.spreads for f in finest for a in aligns
                                        if (s, f, a) != (1, None, True)]
        for spread, level, align in variants:
            rows.append({"capture": capture.name, **measure(scene, spread, align, level)})
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
