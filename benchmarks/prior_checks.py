"""The depth prior's checks on the real-priors scenes, measured without training.

    OMP_NUM_THREADS=1 python benchmarks/prior_checks.py [--scenes skating,truck,umbrella]
                                                       [--data data/synthetic_real]

Per scene (written as a real capture comes, `python -m baselines.synthetic --priors real
--scene_scale 50`, when missing), with the host's sparse points (SIFT triangulated with the known
cameras, as a run gets them):

- the affine fits' residual at the sparse points (reflow_plugin.disparity), median over frames:
  inliers in sample, every point in sample, and held out by image region (what
  --canonical_max_fit_residual reads, canonical/check.py);
- the smooth correction (reflow_plugin.disparity_field): frames where it is kept, its held-out
  residual before / after, and the median true depth error of the frame's disparity as a run
  reads it (the affine fit of the corrected map), against the uncorrected map's;
- the anchored inverse-depth alignment WITHOUT sparse points (the bounds alone): the static
  cloud's median depth over the true depth, with and without the scale gauge of
  canonical/inverse.py (SCALE_WEIGHT 0 = without).

Prints one Markdown table. About a minute per scene on one thread.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from baselines.data import load_scene  # noqa: E402
from baselines.data.triangulation import triangulate_static_points  # noqa: E402
from baselines.synthetic import Priors, get_scene, simulate  # noqa: E402
from reflow_plugin.canonical import CanonicalOptions, build_canonical_space  # noqa: E402
from reflow_plugin.canonical import inverse  # noqa: E402
from reflow_plugin.disparity import fit_frames, project  # noqa: E402
from reflow_plugin.disparity_field import correct_disparity  # noqa: E402

SCALE = 50.0


def _median(values) -> float:
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else float("nan")


def _true_depth(path: Path, camera) -> np.ndarray:
    return np.load(path / "gt" / "depth" / f"{camera.image_name}.npy").astype(np.float64)


def _depth_error(path: Path, camera, disparity: np.ndarray, points: np.ndarray) -> float:
    """Median |depth / true depth - 1| of `disparity` under its own affine fit to the points."""
    fit = fit_frames([camera], [disparity], points)[0]
    return float(np.nanmedian(np.abs(fit.depth(disparity) / _true_depth(path, camera) - 1)))


def _static_ratio(path: Path, scene, weight: float) -> float:
    """Median static-cloud depth / true depth, bounds only (no sparse point), gauge weight `weight`."""
    cameras = scene.train_cameras
    masks = [c.evaluation_mask.numpy() > 0.5 for c in cameras]
    saved, inverse.SCALE_WEIGHT = inverse.SCALE_WEIGHT, weight
    try:
        space = build_canonical_space(scene, masks, CanonicalOptions(cache=False, max_side=32), anchors=None)
    finally:
        inverse.SCALE_WEIGHT = saved
    ratios = []
    for cam in cameras:
        x, y, z = project(space.static.points, cam)
        col, row = np.floor(x).astype(int), np.floor(y).astype(int)
        ok = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        ratios.append(z[ok] / _true_depth(path, cam)[row[ok], col[ok]])
    return float(np.median(np.concatenate(ratios)))


def measure(path: Path) -> dict:
    scene = load_scene(path, eval=False)
    cameras = scene.train_cameras
    points = triangulate_static_points(cameras, seed=0).points
    disparities = [c.disparity.numpy().astype(np.float64) for c in cameras]
    fits = [f for f in fit_frames(cameras, disparities, points) if f.source == "sparse"]
    reports, before, after = [], [], []
    for cam, disparity in zip(cameras, disparities):
        corrected, report = correct_disparity(cam, disparity, points)
        reports.append(report)
        before.append(_depth_error(path, cam, disparity, points))
        after.append(_depth_error(path, cam, corrected, points))
    return {"frames": len(cameras), "points": len(points),
            "inliers": _median(f.residual for f in fits), "all": _median(f.residual_all for f in fits),
            "held_out": _median(f.held_out for f in fits),
            "kept": sum(r["corrected"] for r in reports),
            "field_before": _median(r.get("held_out_before") for r in reports),
            "field_after": _median(r.get("held_out_after") for r in reports if r["corrected"]),
            "error_affine": _median(before), "error_field": _median(after),
            "ratio_without": _static_ratio(path, scene, 0.0), "ratio_with": _static_ratio(path, scene, inverse.SCALE_WEIGHT)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="skating,truck,umbrella")
    parser.add_argument("--data", type=Path, default=Path("data/synthetic_real"))
    args = parser.parse_args(argv)
    print("| scene | frames | points | fit residual: inliers / all (in sample) / held out | field kept | field held "
          "out: before / after | true depth error: affine / + field | no sparse point: depth ratio without / "
          "with gauge |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.scenes.split(","):
        path = args.data / name
        if not (path / "scene.json").is_file():
            simulate(get_scene(name), path, progress=False, priors=Priors.real(), scene_scale=SCALE)
        m = measure(path)
        print(f"| {name} | {m['frames']} | {m['points']} | {m['inliers']:.2%} / {m['all']:.2%} / {m['held_out']:.2%} "
              f"| {m['kept']}/{m['frames']} | {m['field_before']:.2%} / {m['field_after']:.2%} "
              f"| {m['error_affine']:.2%} / {m['error_field']:.2%} | {m['ratio_without']:.3f} / {m['ratio_with']:.3f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
