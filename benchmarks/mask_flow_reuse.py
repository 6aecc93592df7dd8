"""Motion-mask estimation with each frame pair's DIS flows shared by both frames, against each
frame running its own pairs (the code before `motion_masks.PairFlows`), in one process.

    nice -n 5 python benchmarks/mask_flow_reuse.py -s data/real/davis_dog [-r 2] [--rounds 3] [--frames 40]

Loads the capture's training views as train.py does (`--eval`, `-r`), pairs them as ReFlow's
estimate does (`reflow_plugin.labels.pairing_sequences`: time order, or each rig camera's frames
on a wide rig) and times `estimate_motion_masks` both ways, alternating, for `--rounds` rounds.
Prints the median seconds, their ratio, the DIS pair runs of each, and whether the masks are
identical (they must be: the shared path returns the same flows, swapped).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from baselines.data import load_scene, motion_masks  # noqa: E402
from reflow_plugin.labels import pairing_sequences  # noqa: E402


class EveryRequest(motion_masks.PairFlows):
    """The reference: every request runs DIS for its ordered pair (nothing shared)."""

    def __call__(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        self.computed += 1
        return motion_masks.flow_pair(self.images[a], self.images[b])


def estimate(sequences: list[dict], flows_class: type) -> tuple[float, int, list[np.ndarray]]:
    """(seconds, DIS pair runs, masks) of the estimate over every pairing sequence."""
    runs = []

    class Counted(flows_class):
        def __init__(self, images):
            super().__init__(images)
            runs.append(self)

    shared_class = motion_masks.PairFlows
    motion_masks.PairFlows = Counted
    try:
        start = time.perf_counter()
        masks = [mask for seq in sequences
                 for mask in motion_masks.estimate_motion_masks(seq["images"], seq["Ks"], seq["viewmats"])[0]]
        seconds = time.perf_counter() - start
    finally:
        motion_masks.PairFlows = shared_class
    return seconds, sum(r.computed for r in runs), masks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-s", "--source", type=Path, required=True, help="dataset folder")
    parser.add_argument("-r", "--resolution", type=int, default=2, help="train.py -r")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of both variants")
    parser.add_argument("--frames", type=int, default=0, help="first N frames of each sequence (0: all)")
    args = parser.parse_args(argv)
    if not args.source.is_dir():
        print(f"mask_flow_reuse: {args.source} is not a folder", file=sys.stderr)
        return 2
    scene = load_scene(args.source, resolution=args.resolution, eval=True)
    cameras = [c.to("cpu") for c in scene.train_cameras]
    sequences = []
    for order in pairing_sequences(cameras):
        order = order[:args.frames] if args.frames > 0 else order
        sequences.append({"images": [cameras[i].image.numpy() for i in order],
                          "Ks": [cameras[i].K.double().numpy() for i in order],
                          "viewmats": [cameras[i].viewmat.double().numpy() for i in order]})
    frames = sum(len(s["images"]) for s in sequences)
    height, width = sequences[0]["images"][0].shape[:2]
    print(f"{args.source.name}: {frames} frames in {len(sequences)} pairing sequence(s), {width}x{height}")
    times = {"shared": [], "every request": []}
    runs, masks = {}, {}
    for _ in range(args.rounds):
        for name, flows_class in (("shared", motion_masks.PairFlows), ("every request", EveryRequest)):
            seconds, runs[name], masks[name] = estimate(sequences, flows_class)
            times[name].append(seconds)
    same = all(np.array_equal(a, b) for a, b in zip(masks["shared"], masks["every request"]))
    print("| variant | median s | DIS pair runs |\n|---|---:|---:|")
    for name in times:
        print(f"| {name} | {statistics.median(times[name]):.2f} | {runs[name]} |")
    ratio = statistics.median(times["shared"]) / statistics.median(times["every request"])
    print(f"shared / every request: {ratio:.2f}x over {args.rounds} rounds; masks identical: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
