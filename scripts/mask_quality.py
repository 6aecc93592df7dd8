#!/usr/bin/env python3
"""How good were a run's estimated motion masks? Against the simulator's exact ones.

    python scripts/mask_quality.py output/suite_real_q/*/reflow

For each run folder whose ReFlow plugin estimated masks (`RUN/reflow/motion_masks/*.png`), reads
the dataset named in the run's `cfg_args` (`source_path`) and compares with its
`gt/motion_masks/*.png` (written by the simulator; training never sees them): recall (the share of
truly moving pixels inside the estimate), precision, IoU, and the mean mask area per frame, pooled
over the training frames. Prints one Markdown table.
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import cv2
import numpy as np


def mask_scores(estimated: list[np.ndarray], truth: list[np.ndarray]) -> dict[str, float]:
    """Pooled recall, precision, IoU and mean areas (px per frame) of bool masks [H, W], paired."""
    tp = sum(int((e & t).sum()) for e, t in zip(estimated, truth))
    fp = sum(int((e & ~t).sum()) for e, t in zip(estimated, truth))
    fn = sum(int((~e & t).sum()) for e, t in zip(estimated, truth))
    frames = max(len(truth), 1)
    return {"recall": tp / max(tp + fn, 1), "precision": tp / max(tp + fp, 1), "iou": tp / max(tp + fp + fn, 1),
            "true_px": (tp + fn) / frames, "estimated_px": (tp + fp) / frames}


def source_of(run: Path) -> Path:
    """The dataset folder a run trained on (its cfg_args' source_path)."""
    text = (run / "cfg_args").read_text()
    found = re.search(r"source_path='([^']*)'", text)
    if not found:
        raise SystemExit(f"mask_quality: no source_path in {run / 'cfg_args'}")
    return Path(found.group(1))


def read(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"mask_quality: cannot read {path}")
    return image > 127


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--data", type=Path, help="read each run's scene from DATA/<scene folder name> instead "
                                                  "(when the dataset moved since training)")
    args = parser.parse_args(argv)
    print("| run | recall | precision | IoU | true px / frame | estimated px / frame |")
    print("|---|---:|---:|---:|---:|---:|")
    for run in args.runs:
        folder = run / "reflow" / "motion_masks"
        names = sorted(folder.glob("*.png"))
        if not names:
            print(f"| {run} | no estimated masks | | | | |")
            continue
        source = source_of(run)
        truth_dir = (args.data / source.name if args.data else source) / "gt" / "motion_masks"
        scores = mask_scores([read(p) for p in names], [read(truth_dir / p.name) for p in names])
        print(f"| {run} | {scores['recall']:.2f} | {scores['precision']:.2f} | {scores['iou']:.2f} | "
              f"{scores['true_px']:.0f} | {scores['estimated_px']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
