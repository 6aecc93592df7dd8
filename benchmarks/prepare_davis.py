"""`python -m baselines.prepare` on the DAVIS captures of the registry: registration and mask quality.

    nice -n 5 python benchmarks/prepare_davis.py --clone CLONE_OF_MathLee/EOR-VOS [--data data/real]
                                                 [--clips blackswan,dog] [--redo]

For each DAVIS clip of `benchmarks/real_captures.py` (the `davis_*` captures) not yet set up
under `--data`, runs the capture's setup (extract frames + annotations at the pinned commit,
prepare with the capture's flags, ground-truth masks), one clip at a time; then prints one
Markdown table: frames registered / extracted, mean reprojection error, points, the mapper kept,
prepare's wall seconds, and prepare's AUTO motion masks (what ReFlow trains with: the dataset's
`motion_masks/` when the report says they are the post-mapping ones, `"stage": "posed"`, else the
pre-SfM `.prepare/masks/` of every extracted frame) against the DAVIS annotations (binarised: any object > 0):
IoU, precision and recall pooled over the clip's frames. A clip prepare cannot register is a
row with the error. The table and the raw figures also go to `--data/prepare_davis.{md,json}`.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.real_captures import (CAPTURES, DAVIS_REPO, DEFAULT_DATA, Capture, CaptureError,  # noqa: E402
                                      dataset_dir, is_ready, setup, truth_dir)

COLUMNS = ("clip", "registered", "reproj px", "points", "mapper", "seconds", "IoU", "precision", "recall")


def davis_captures(names: str | None) -> list[Capture]:
    """The registry's DAVIS captures, or those named (clip names, with or without `davis_`)."""
    davis = {c.name: c for c in CAPTURES.values() if c.repo == DAVIS_REPO}
    if not names:
        return list(davis.values())
    chosen = ["davis_" + n.strip().removeprefix("davis_").replace("-", "_") for n in names.split(",") if n.strip()]
    unknown = [n for n in chosen if n not in davis]
    if unknown:
        raise CaptureError(f"unknown DAVIS clip(s) {unknown}; known: {', '.join(davis)}")
    return [davis[n] for n in chosen]


def mask_scores(masks: list[np.ndarray], truth: list[np.ndarray]) -> dict[str, float]:
    """IoU, precision and recall of bool masks against bool truth, pixels pooled over frames."""
    hit = sum(int((m & t).sum()) for m, t in zip(masks, truth))
    predicted = sum(int(m.sum()) for m in masks)
    actual = sum(int(t.sum()) for t in truth)
    union = predicted + actual - hit
    return {"IoU": hit / union if union else 1.0, "precision": hit / predicted if predicted else 0.0,
            "recall": hit / actual if actual else 1.0}


def auto_mask_scores(capture: Capture, data_root: Path) -> dict[str, float] | None:
    """Scores of prepare's auto masks against the annotations, or None: the dataset's posed or
    background masks (registered frames) when it has them, else the pre-SfM ones (every extracted
    frame)."""
    mask_dir = dataset_dir(capture, data_root) / ".prepare" / "masks"
    report_path = dataset_dir(capture, data_root) / "prepare_report.json"
    if report_path.is_file() and json.loads(report_path.read_text()).get("masks", {}).get("stage") in ("posed",
                                                                                                 "background"):
        mask_dir = dataset_dir(capture, data_root) / "motion_masks"
    annotations = sorted(truth_dir(capture, data_root).glob("*.png"))
    if not mask_dir.is_dir() or not annotations:
        return None
    masks, truth = [], []
    for path in sorted(mask_dir.glob("*.png")):
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0
        labels = cv2.imread(str(annotations[int(path.stem)]), cv2.IMREAD_GRAYSCALE)
        truth.append(cv2.resize((labels > 0).astype(np.uint8), mask.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0)
        masks.append(mask)
    return mask_scores(masks, truth)


def row(capture: Capture, data_root: Path, error: str | None = None) -> dict:
    """One table row from the prepared dataset's report (or the error that stopped prepare)."""
    clip = capture.folder.rsplit("/", 1)[-1]
    result: dict = {"clip": clip, "capture": capture.name, "error": error}
    report_path = dataset_dir(capture, data_root) / "prepare_report.json"
    if error is None and report_path.is_file():
        report = json.loads(report_path.read_text())
        result.update(registered=report["registered_frames"], extracted=report["extracted_frames"],
                      reprojection_px=report["mean_reprojection_error_px"], points=report["points"],
                      mapper=report.get("mapper"), seconds=report["wall_seconds"],
                      reused=report["reused_stages"])
    result["masks"] = auto_mask_scores(capture, data_root)
    return result


def table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        m = r["masks"] or {}
        scores = [f"{m[k]:.2f}" if k in m else "-" for k in ("IoU", "precision", "recall")]
        if r.get("registered") is None:
            lines.append(f"| {r['clip']} | failed: {r['error']} | - | - | - | - | " + " | ".join(scores) + " |")
            continue
        mapper = r["mapper"] or {}
        used = mapper.get("used", "incremental")
        reprojection = f"{r['reprojection_px']:.2f}"
        if mapper.get("fixed_centre") is not None:  # one centre, rotations from homographies: no reprojection
            used += f" ({mapper['reason']})"
            reprojection = "-"
        elif mapper.get("global") is not None:  # both ran: say what the other registered
            other = "global" if used == "incremental" else "incremental"
            used += f" ({other}: {mapper[other][0]})"
        lines.append(f"| {r['clip']} | {r['registered']}/{r['extracted']} | {reprojection} | "
                     f"{r['points']} | {used} | {r['seconds']:.0f} | " + " | ".join(scores) + " |")
    done = [r for r in rows if r.get("registered") is not None]
    good = sum(r["registered"] >= 0.8 * r["extracted"] for r in done)
    fixed = sum(r["registered"] >= 0.8 * r["extracted"] and (r["mapper"] or {}).get("fixed_centre") is not None
                for r in done)
    placed = f"{good} of {len(rows)} clips with >= 80% of frames registered" + (
        f" ({fixed} of them with a fixed centre, not SfM)" if fixed else "")
    ious = [r["masks"]["IoU"] for r in rows if r["masks"]]
    lines.append("")
    lines.append(f"{placed}; auto-mask IoU mean {np.mean(ious):.2f} over {len(ious)} clips" if ious else placed)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clone", type=Path, help="a clone (plain or bare) of MathLee/EOR-VOS; needed to set up clips")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="data root of the captures (default data/real)")
    parser.add_argument("--clips", help="comma list of clips (default: all 13)")
    parser.add_argument("--redo", action="store_true", help="set up again the clips already prepared")
    args = parser.parse_args(argv)
    try:
        captures = davis_captures(args.clips)
        todo = [c for c in captures if args.redo or not is_ready(c, args.data)]
        if todo and args.clone is None:
            raise CaptureError(f"{len(todo)} clip(s) not set up under {args.data} ({todo[0].name}, ...): give --clone")
    except CaptureError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    rows = []
    for capture in captures:
        error = None
        if capture in todo:
            if args.redo:
                shutil.rmtree(dataset_dir(capture, args.data), ignore_errors=True)
            start = time.perf_counter()
            try:
                setup(capture, args.clone, args.data)
            except subprocess.CalledProcessError:
                error = "prepare exited with an error (see above)"
            except CaptureError as err:
                error = str(err)
            print(f"{capture.name}: {time.perf_counter() - start:.0f} s", flush=True)
        rows.append(row(capture, args.data, error))
    load = os.getloadavg()
    text = (f"{time.strftime('%Y-%m-%d', time.gmtime())}, {os.cpu_count()} cores, load {load[0]:.1f} "
            f"{load[1]:.1f} {load[2]:.1f} at the end\n\n" + table(rows))
    print(text)
    args.data.mkdir(parents=True, exist_ok=True)
    (args.data / "prepare_davis.md").write_text(text + "\n")
    (args.data / "prepare_davis.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
