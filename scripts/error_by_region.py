#!/usr/bin/env python3
"""Where does run B lose (or gain) against run A? Test-view error binned by distance to the motion mask.

    python scripts/error_by_region.py output/ablation/skating/sep output/ablation/skating/sep_fullfm \
        -s data/synthetic/skating
    python scripts/error_by_region.py RUN_A RUN_B -s SCENE --split train   # after render.py --skip_test

`--split train` compares the TRAINING views (`train/ours_N`, written by `python render.py -m RUN
--skip_test --skip_video`): a method that loses inside the mask on the training views too cannot
fit the motion, one that fits them and loses on held-out views does not generalise it.

Both runs must be evaluated on the same scene (their `test/ours_N/{renders,gt}` folders, written by
train.py / render.py). Each test pixel goes to one region: inside the view's motion mask, or in a
band of distances (pixels) to the nearest mask pixel outside it. Per region: its share of the
pixels, PSNR of A and of B over the region's pixels of all test views, and the region's share of
the change of the summed squared error outside the mask (how much of B's static-region loss or gain
sits in that band). The question it answers: is a static-PSNR change concentrated at the moving
objects' boundaries (occlusion effects) or spread over the static scene?
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from baselines.data.loader import load_scene  # noqa: E402

BANDS_PX = (2.0, 5.0, 10.0, 20.0)


def latest_test_folder(run: Path, iteration: int | None, split: str = "test") -> Path:
    """`run/<split>/ours_N` for the given N, else the highest N present."""
    folders = sorted((run / split).glob("ours_*"), key=lambda p: int(p.name.split("_")[1]))
    if iteration is not None:
        folders = [f for f in folders if f.name == f"ours_{iteration}"]
    if not folders:
        raise SystemExit(f"error_by_region: no {split}/ours_{iteration or 'N'} folder in {run}")
    return folders[-1]


def read_views(folder: Path) -> list[np.ndarray]:
    """The folder's `renders/*.png` (or `gt/*.png`) as float [H, W, 3] in [0, 1], in name order."""
    files = sorted(folder.glob("*.png"))
    if not files:
        raise SystemExit(f"error_by_region: no PNG in {folder}")
    return [cv2.imread(str(f), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float64) / 255.0 for f in files]


def region_labels(mask: np.ndarray) -> np.ndarray:
    """[H, W] int: 0 inside the mask, 1.. for the distance bands outside it, len(BANDS_PX)+1 beyond."""
    outside = (~mask).astype(np.uint8)
    distance = cv2.distanceTransform(outside, cv2.DIST_L2, 5) if mask.any() else np.full(mask.shape, np.inf)
    labels = 1 + np.searchsorted(np.asarray(BANDS_PX), distance, side="left")
    labels[mask] = 0
    return labels


def region_names() -> list[str]:
    edges = (0.0, *BANDS_PX)
    names = ["inside the mask"] + [f"{a:g}-{b:g} px from it" for a, b in zip(edges[:-1], edges[1:])]
    return names + [f"> {BANDS_PX[-1]:g} px"]


def compare(run_a: Path, run_b: Path, source: Path, iteration: int | None, split: str = "test") -> str:
    """Markdown table of the per-region comparison (`split`: "test" or "train" views)."""
    folder_a, folder_b = latest_test_folder(run_a, iteration, split), latest_test_folder(run_b, iteration, split)
    renders_a, renders_b = read_views(folder_a / "renders"), read_views(folder_b / "renders")
    gts = read_views(folder_a / "gt")
    scene = load_scene(source, eval=True)
    cameras = scene.train_cameras if split == "train" else scene.test_cameras
    if not (len(renders_a) == len(renders_b) == len(gts) == len(cameras)):
        raise SystemExit(f"error_by_region: view counts differ: A {len(renders_a)}, B {len(renders_b)}, "
                         f"gt {len(gts)}, scene {split} cameras {len(cameras)}")
    n_regions = len(BANDS_PX) + 2
    pixels = np.zeros(n_regions)
    sq_a, sq_b = np.zeros(n_regions), np.zeros(n_regions)
    for cam, a, b, gt in zip(cameras, renders_a, renders_b, gts):
        if cam.evaluation_mask is None:
            raise SystemExit(f"error_by_region: {source} has no motion masks")
        mask = cam.evaluation_mask.cpu().numpy() > 0.5
        if mask.shape != gt.shape[:2]:
            raise SystemExit(f"error_by_region: mask {mask.shape} vs image {gt.shape[:2]}")
        labels = region_labels(mask)
        err_a, err_b = ((a - gt) ** 2).mean(-1), ((b - gt) ** 2).mean(-1)
        pixels += np.bincount(labels.ravel(), minlength=n_regions)
        sq_a += np.bincount(labels.ravel(), weights=err_a.ravel(), minlength=n_regions)
        sq_b += np.bincount(labels.ravel(), weights=err_b.ravel(), minlength=n_regions)

    def psnr(sq: float, n: float) -> float:
        return float(-10.0 * np.log10(max(sq / max(n, 1.0), 1e-12)))

    static_change = (sq_b - sq_a)[1:].sum()
    lines = [f"A = {run_a} ({folder_a.name}), B = {run_b} ({folder_b.name}), {len(gts)} {split} views",
             "", "| region | pixels | PSNR A | PSNR B | B - A | share of the static squared-error change |",
             "|---|---:|---:|---:|---:|---:|"]
    for k, name in enumerate(region_names()):
        share = "" if k == 0 or static_change == 0 else f"{100.0 * (sq_b[k] - sq_a[k]) / static_change:.0f}%"
        pa, pb = psnr(sq_a[k], pixels[k]), psnr(sq_b[k], pixels[k])
        lines.append(f"| {name} | {100.0 * pixels[k] / pixels.sum():.1f}% | {pa:.2f} | {pb:.2f} | {pb - pa:+.2f} | {share} |")
    pa, pb = psnr(sq_a[1:].sum(), pixels[1:].sum()), psnr(sq_b[1:].sum(), pixels[1:].sum())
    lines.append(f"| **outside the mask** | {100.0 * pixels[1:].sum() / pixels.sum():.1f}% | {pa:.2f} | {pb:.2f} | "
                 f"{pb - pa:+.2f} | 100% |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", type=Path)
    parser.add_argument("run_b", type=Path)
    parser.add_argument("-s", "--source", type=Path, required=True, help="the scene both runs were trained on")
    parser.add_argument("--iteration", type=int, default=None, help="ours_N to compare (default: the last)")
    parser.add_argument("--split", choices=("test", "train"), default="test",
                        help="held-out views (default) or the training views (render.py --skip_test first)")
    args = parser.parse_args(argv)
    print(compare(args.run_a, args.run_b, args.source, args.iteration, args.split))
    return 0


if __name__ == "__main__":
    sys.exit(main())
