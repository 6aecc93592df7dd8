"""Generate every named synthetic scene at its default size and print timings and statistics.

    python benchmarks/synthetic.py [--out DIR] [--scenes a,b,...] [--frames N] [--size WxH]

Per scene: frames and size, wall and CPU seconds, dynamic-pixel fraction (motion masks), depth
range, median / max forward-flow magnitude over non-occluded pixels, occluded fraction.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from baselines.synthetic import get_scene, list_scenes, simulate  # noqa: E402
from baselines.synthetic.__main__ import parse_size  # noqa: E402


def scene_stats(root: Path) -> dict:
    """Statistics of a generated scene directory."""
    info = json.loads((root / "scene.json").read_text())
    masks = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 0
             for p in sorted((root / "motion_masks").glob("*.png"))]
    depths = [np.load(p) for p in sorted((root / "gt" / "depth").glob("*.npy"))]
    flows, occluded = [], []
    for path in sorted((root / "gt" / "flow_fwd").glob("*.npy")):
        occ = cv2.imread(str(root / "gt" / "occ_fwd" / f"{path.stem}.png"), cv2.IMREAD_GRAYSCALE)
        flow = np.load(path)
        flows.append(np.linalg.norm(flow, axis=-1)[occ == 0])
        occluded.append((occ > 0).mean())
    magnitudes = np.concatenate(flows)
    return {"effects": info["effects"], "dynamic_fraction": float(np.mean(masks)),
            "depth": (float(min(d.min() for d in depths)), float(max(d.max() for d in depths))),
            "flow_median": float(np.median(magnitudes)), "flow_max": float(magnitudes.max()),
            "occluded": float(np.mean(occluded))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="keep the scenes here (default: a temp dir)")
    parser.add_argument("--scenes", help="comma-separated subset (default: all)")
    parser.add_argument("--frames", type=int)
    parser.add_argument("--size")
    args = parser.parse_args()
    names = args.scenes.split(",") if args.scenes else list(list_scenes())
    overrides = {"frames": args.frames}
    if args.size:
        overrides["width"], overrides["height"] = parse_size(args.size)
    with tempfile.TemporaryDirectory() as tmp:
        base = args.out or Path(tmp)
        print(f"{'scene':<17} {'frames':>6} {'size':>8} {'wall s':>7} {'cpu s':>6} {'dyn %':>6} "
              f"{'depth range':>13} {'flow med/max px':>16} {'occ %':>6}")
        for name in names:
            spec = get_scene(name, **overrides)
            wall, cpu = time.perf_counter(), time.process_time()
            root = simulate(spec, base / name, progress=False)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            s = scene_stats(root)
            print(f"{name:<17} {spec.frames:>6} {spec.width:>4}x{spec.height:<3} {wall:>7.2f} "
                  f"{cpu:>6.2f} {100 * s['dynamic_fraction']:>6.1f} "
                  f"{s['depth'][0]:>6.2f}-{s['depth'][1]:<6.2f} "
                  f"{s['flow_median']:>7.2f}/{s['flow_max']:<8.2f} {100 * s['occluded']:>6.1f}")


if __name__ == "__main__":
    main()
