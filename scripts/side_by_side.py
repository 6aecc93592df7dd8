"""Ground truth | run 1 | run 2 ... of held-out views, as one labelled PNG.

    python scripts/side_by_side.py output/suite/skating/baseline output/suite/skating/reflow \
        --views 1 3 --scale 3 -o docs/images/skating_test.png

Reads `<run>/test/ours_<N>/renders` (the latest iteration of each run) and the first run's `gt`.
Rows are views, columns ground truth then the runs, labelled with the folder name (or `--labels`) and the view's
PSNR (and PSNR-dynamic when `per_view.json` has it).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np


def latest_test_dir(run: Path) -> Path:
    dirs = sorted((run / "test").glob("ours_*"), key=lambda p: int(p.name.split("_")[1]))
    if not dirs:
        raise SystemExit(f"error: no test renders under {run / 'test'} (train with --eval first)")
    return dirs[-1]


def label(image: np.ndarray, text: str) -> np.ndarray:
    out = image.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def view_metrics(run: Path, method: str, name: str) -> str:
    path = run / "per_view.json"
    if not path.is_file():
        return ""
    values = json.loads(path.read_text()).get(method, {})
    psnr = values.get("PSNR", {}).get(name)
    dyn = values.get("PSNR-dynamic", {}).get(name)
    text = f" {psnr:.1f} dB" if psnr is not None else ""
    return text + (f" (dyn {dyn:.1f})" if dyn is not None else "")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--views", nargs="+", type=int, default=[0])
    parser.add_argument("--scale", type=int, default=2, help="nearest-neighbour upscaling for readability")
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--labels", nargs="+", help="one column title per run (default: the run folders' names)")
    args = parser.parse_args(argv)
    if args.labels is not None and len(args.labels) != len(args.runs):
        parser.error(f"--labels: {len(args.labels)} given for {len(args.runs)} runs")
    titles = args.labels or [run.name for run in args.runs]
    test_dirs = [latest_test_dir(r) for r in args.runs]
    rows = []
    for view in args.views:
        name = f"{view:05d}.png"
        gt = cv2.imread(str(test_dirs[0] / "gt" / name))
        if gt is None:
            raise SystemExit(f"error: no ground truth {test_dirs[0] / 'gt' / name}")
        size = (gt.shape[1] * args.scale, gt.shape[0] * args.scale)
        cells = [label(cv2.resize(gt, size, interpolation=cv2.INTER_NEAREST), "ground truth")]
        for run, test_dir, title in zip(args.runs, test_dirs, titles):
            render = cv2.imread(str(test_dir / "renders" / name))
            if render is None:
                raise SystemExit(f"error: no render {test_dir / 'renders' / name}")
            text = title + view_metrics(run, test_dir.name, name)
            cells.append(label(cv2.resize(render, size, interpolation=cv2.INTER_NEAREST), text))
        rows.append(np.concatenate(cells, axis=1))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.output), np.concatenate(rows, axis=0))
    print(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
