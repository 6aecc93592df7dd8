"""Quality of `prepare`'s automatic motion masks on prepared DAVIS clips, mask stage only.

    nice -n 5 python benchmarks/mask_quality.py --data /work/realdata [--clips dog,libby] [--json OUT.json]
    nice -n 5 python benchmarks/mask_quality.py --data /work/realdata --posed     # the post-mapping masks
    nice -n 5 python benchmarks/mask_quality.py --data /work/realdata --background   # --masks background

For each clip folder `<data>/davis_<clip>/` (written by `benchmarks/prepare_davis.py`: `images/`
the extracted frames, `gt/motion_masks/` the DAVIS annotations at the frames' size), runs only the
mask stage of `python -m baselines.prepare` on the frames (`measure_parallax` for the background
motion that picks the pairs, then `baselines.prepare.masks.motion_masks(images, "auto", ...)`: no
feature matching, no SfM) and prints one Markdown table: IoU, precision and recall against the
annotations (pixels pooled over the clip's frames, as in docs/DATASETS.md) and the mask stage's
seconds. Clips are split into a TUNING half (the clips the method's constants were chosen on)
and HELD-OUT clips, with a mean for each, so that a change can be judged on clips it was not
tuned on. Clips without camera motion (breakdance, drift-chicane) have no frames and are skipped.

`--posed` scores the post-mapping stage instead (`baselines.prepare.remask.posed_masks`): the
cameras and sparse points are read from each clip's `sparse/0/`, the frames from `images/` (the
registered frames, which the annotations are matched to by name). `--background` scores
`--masks background`: the pre-SfM masks of the clip's frames, then background subtraction along
the homographies of neighbouring frames (`baselines.prepare.background.moving_camera_masks`).
Nothing is written into the clip folders.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from baselines.prepare.background import moving_camera_masks  # noqa: E402
from baselines.prepare.masks import motion_masks  # noqa: E402
from baselines.prepare.parallax import measure_parallax  # noqa: E402
from baselines.prepare.remask import posed_masks, read_posed_dataset  # noqa: E402
from benchmarks.prepare_davis import mask_scores  # noqa: E402

TUNING = ("dog", "libby", "goat", "cows", "scooter_black")
HELD_OUT = ("blackswan", "bmx_trees", "kite_surf", "motocross_jump", "paragliding_launch", "soapbox")


def read_clip(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(frames [H, W, 3] uint8 BGR, annotations [H, W] bool) of a prepared clip, in frame order."""
    frames = sorted((folder / "images").glob("*.png"))
    images = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in frames]
    truth = []
    for path, image in zip(frames, images):
        labels = cv2.imread(str(folder / "gt" / "motion_masks" / path.name), cv2.IMREAD_GRAYSCALE)
        if labels is None:
            raise FileNotFoundError(f"{folder}: no annotation gt/motion_masks/{path.name} for frame {path.name}")
        truth.append(cv2.resize((labels > 0).astype(np.uint8), image.shape[1::-1], interpolation=cv2.INTER_NEAREST) > 0)
    return images, truth


def evaluate(folder: Path, posed: bool = False, background: bool = False) -> dict:
    """Scores and seconds of the auto masks of one clip folder (`posed`: the post-mapping masks;
    `background`: `--masks background`'s, from the pre-SfM masks of the same frames)."""
    images, truth = read_clip(folder)
    start = time.perf_counter()
    motion = measure_parallax(images).frame_motion_px
    if background:
        pre_sfm, _ = motion_masks(images, "auto", motion, progress=False)
        masks = moving_camera_masks(images, pre_sfm)
    elif posed:
        names, frames, Ks, viewmats, views = read_posed_dataset(folder)
        index = {path.name: k for k, path in enumerate(sorted((folder / "images").glob("*.png")))}
        truth = [truth[index[name]] for name in names]
        masks = posed_masks(frames, Ks, viewmats, views, motion, progress=False)
    else:
        masks, _ = motion_masks(images, "auto", motion, progress=False)
    seconds = time.perf_counter() - start
    return {**mask_scores(masks, truth), "seconds": seconds, "frames": len(images), "frame_motion_px": motion}


def table(results: dict[str, dict]) -> str:
    """Markdown table: tuning clips, then held-out ones, each group with its mean."""
    lines = ["| clip | set | frames | IoU | precision | recall | seconds |", "|---|---|---|---|---|---|---|"]
    for group, names in (("tuning", TUNING), ("held-out", HELD_OUT)):
        rows = [(n, results[n]) for n in names if n in results]
        for name, r in rows:
            lines.append(f"| {name.replace('_', '-')} | {group} | {r['frames']} | {r['IoU']:.2f} | {r['precision']:.2f} | "
                         f"{r['recall']:.2f} | {r['seconds']:.1f} |")
        if rows:
            mean = {k: np.mean([r[k] for _, r in rows]) for k in ("IoU", "precision", "recall", "seconds")}
            lines.append(f"| **mean** | {group} | | **{mean['IoU']:.2f}** | {mean['precision']:.2f} | "
                         f"{mean['recall']:.2f} | {mean['seconds']:.1f} |")
    others = [n for n in results if n not in TUNING + HELD_OUT]
    for name in others:
        r = results[name]
        lines.append(f"| {name.replace('_', '-')} | other | {r['frames']} | {r['IoU']:.2f} | {r['precision']:.2f} | "
                     f"{r['recall']:.2f} | {r['seconds']:.1f} |")
    ious = [r["IoU"] for r in results.values()]
    lines.append("")
    lines.append(f"mean IoU {np.mean(ious):.2f} over {len(ious)} clips")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="folder holding the davis_<clip>/ datasets")
    parser.add_argument("--clips", help="comma list of clips (default: the tuning and held-out clips found)")
    parser.add_argument("--json", type=Path, help="also write the raw figures here")
    parser.add_argument("--posed", action="store_true",
                        help="score the post-mapping masks (cameras and points from each clip's sparse/0)")
    parser.add_argument("--background", action="store_true",
                        help="score --masks background (pre-SfM masks, then background subtraction along the "
                             "homographies of neighbouring frames)")
    args = parser.parse_args(argv)
    names = ([n.strip().removeprefix("davis_").replace("-", "_") for n in args.clips.split(",") if n.strip()]
             if args.clips else list(TUNING + HELD_OUT))
    folders = {n: args.data / f"davis_{n}" for n in names}
    missing = [str(f) for f in folders.values() if not (f / "images").is_dir() or not (f / "gt" / "motion_masks").is_dir()
               or (args.posed and not (f / "sparse" / "0").is_dir())]
    if args.clips and missing:
        print(f"error: no prepared clip (images/, gt/motion_masks/{' and sparse/0/' if args.posed else ''}) at {missing[0]}",
              file=sys.stderr)
        return 2
    folders = {n: f for n, f in folders.items() if str(f) not in missing}
    if not folders:
        print(f"error: no prepared DAVIS clip under {args.data} (expected davis_<clip>/images and gt/motion_masks)",
              file=sys.stderr)
        return 2
    results = {}
    for name, folder in folders.items():
        results[name] = evaluate(folder, args.posed, args.background)
        r = results[name]
        print(f"{name}: IoU {r['IoU']:.3f} precision {r['precision']:.3f} recall {r['recall']:.3f} "
              f"({r['seconds']:.1f} s)", file=sys.stderr, flush=True)
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
