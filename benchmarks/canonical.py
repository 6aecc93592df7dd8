"""Cost of the canonical-space alignment versus the number of frames: full pair graph vs coarse-to-fine.

    OMP_NUM_THREADS=1 python benchmarks/canonical.py [--frames 24 48 96 192] [--size 32x24] [--iters 100]
                                                     [--full_max 48] [--repeats 1]

Each run is a fresh process (so its peak RSS is its own) that simulates a skating scene with N
frames at a small size, then builds the canonical space with the depth provider (simulator depth,
5% scale drift, 1% noise) and fixed cameras: `mode=full` aligns all N (N - 1) / 2 pairs in one
graph, `mode=coarse_to_fine` the keyframe graph then each clip (clip_len 25, window 4). Seconds
are the alignment's own (provider + initialisation + Adam), peak memory the process's max RSS.
The full graph is skipped beyond --full_max frames (O(N^2) pairs). Prints one table of medians.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(frames: int, size: str, mode: str, iters: int) -> dict:
    """One measurement in this (fresh) process."""
    import resource

    sys.path.insert(0, str(ROOT))
    from baselines.data import load_scene
    from baselines.synthetic import get_scene, simulate
    from reflow_plugin.canonical import CanonicalOptions, build_canonical_space

    width, height = (int(v) for v in size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        path = simulate(get_scene("skating", frames=frames, width=width, height=height, seed=0),
                        Path(tmp) / "scene", progress=False)
        scene = load_scene(path, eval=False)
        masks = [c.mask.numpy() > 0.5 for c in scene.train_cameras]
        options = CanonicalOptions(depth_source="gt", drift=0.05, noise=0.01, mode=mode, iterations=iters,
                                   cache=False, max_side=max(width, height))
        space = build_canonical_space(scene, masks, options)
    return {"seconds": space.report["seconds"]["alignment"], "edges": space.report["alignment"]["edges"],
            "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def measure(frames: int, size: str, mode: str, iters: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"), OMP_WAIT_POLICY="PASSIVE")
    out = subprocess.run([sys.executable, __file__, "--child", f"{frames},{size},{mode},{iters}"], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[24, 48, 96, 192])
    parser.add_argument("--size", default="32x24")
    parser.add_argument("--iters", type=int, default=100)
    parser.add_argument("--full_max", type=int, default=48, help="skip the full graph beyond this many frames")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        frames, size, mode, iters = args.child.split(",")
        print(json.dumps(child(int(frames), size, mode, int(iters))))
        return
    print(f"canonical space alignment, {args.size} px, {args.iters} Adam iterations per graph, "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '1')}, median of {args.repeats}")
    print("| frames | full graph: pairs | s | peak MiB | coarse-to-fine: pairs | s | peak MiB |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for n in args.frames:
        cells = []
        for mode in ("full", "coarse_to_fine"):
            if mode == "full" and n > args.full_max:
                cells.append(f"skipped ({n * (n - 1) // 2}) | - | -")
                continue
            runs = [measure(n, args.size, mode, args.iters) for _ in range(args.repeats)]
            cells.append(f"{runs[0]['edges']} | {statistics.median(r['seconds'] for r in runs):.1f} | "
                         f"{statistics.median(r['peak_mib'] for r in runs):.0f}")
        print(f"| {n} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
