#!/usr/bin/env python3
"""What `--time_outside` changes on trained runs: test PSNR under each mode, same models.

    python scripts/time_outside.py output/ablation/*/*          # any trained runs (baseline or plugin)
    python scripts/time_outside.py RUN... --json out.json

A run's test views whose time lies outside its training views' span (with the simulator's split,
frame 0 is held out, one frame before the first training frame) are rendered with the deformation
extrapolated, held at the nearest trained time, or held with the centres moved on linearly
(`GaussianModel.set_time_span`). Training never samples outside the span, so the trained model is
the same whichever mode it ran with: this re-renders each run's last saved iteration under every
mode. Prints, per run, the mean test PSNR and the PSNR of the views outside the span per mode,
and the mean over runs.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()

import torch  # noqa: E402

from baselines.fourdgs.app import load_run  # noqa: E402
from baselines.fourdgs.evaluate import evaluate_cameras  # noqa: E402
from baselines.fourdgs.gaussian_model import TIME_OUTSIDE_MODES  # noqa: E402


def psnr_by_mode(run: Path) -> dict[str, object]:
    """{"outside": [view names], mode: {"mean": PSNR, "outside": mean PSNR of those views or None}}."""
    try:
        trainer = load_run(["-m", str(run)]).trainer
    except FileNotFoundError as exc:
        raise SystemExit(f"time_outside: {exc}") from None
    model, cams = trainer.ctx.model, trainer.test_cameras
    if model.time_span is None:
        raise SystemExit(f"time_outside: {run} has no training views, hence no time span")
    lo, hi = model.time_span
    outside = [c.image_name for c in cams if not lo <= c.time <= hi]
    row: dict[str, object] = {"run": str(run), "outside": outside}
    for mode in TIME_OUTSIDE_MODES:
        model.set_time_span((lo, hi), mode)
        with torch.no_grad():
            result = evaluate_cameras(model, cams, "fine", trainer.ctx.background, trainer.pipe.backend)
        views = [v["PSNR"] for name, v in zip((c.image_name for c in cams), result.per_view.values())
                 if name in outside]
        row[mode] = {"mean": result.mean["PSNR"], "outside": sum(views) / len(views) if views else None}
    trainer.run_log.close()
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="trained model folders")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    rows = [psnr_by_mode(run) for run in args.runs]
    header = " | ".join(f"{m} mean / outside" for m in TIME_OUTSIDE_MODES)
    print(f"| run | views outside | {header} |")
    print("|---|---|" + "---:|" * len(TIME_OUTSIDE_MODES))

    def cell(entry: dict) -> str:
        outside = "-" if entry["outside"] is None else f"{entry['outside']:.2f}"
        return f"{entry['mean']:.2f} / {outside}"

    for row in rows:
        cells = " | ".join(cell(row[m]) for m in TIME_OUTSIDE_MODES)
        print(f"| {row['run']} | {', '.join(row['outside']) or '-'} | {cells} |")
    means = {m: sum(r[m]["mean"] for r in rows) / len(rows) for m in TIME_OUTSIDE_MODES}
    print(f"| **mean of {len(rows)} runs** | | " + " | ".join(f"{means[m]:.2f}" for m in TIME_OUTSIDE_MODES) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
