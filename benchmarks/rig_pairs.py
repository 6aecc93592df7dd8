"""Frame pairing on a wide rig read monocularly (reflow_plugin.rig): by time versus by camera.

    nice -n 5 python benchmarks/rig_pairs.py -s data/real/panoptic_basketball [-r 4] [--frames 12] [--json OUT]

Loads the capture's training views as train.py does (`--eval`, `-r`; the sparse points: the
dataset's, else triangulated from the training views) and prints three blocks:

- the rig: camera poses, the median angle between consecutive frames' viewing directions and
  whether `wide_rig` calls it wide (>= 10 degrees);
- motion masks (reflow_plugin.labels.estimated_masks, no disparity: the epipolar test) paired
  in time order and paired within each rig camera: mean coverage and, where the views carry
  evaluation-only masks (`extras["eval_mask"]`: panoptic's seg/), IoU / precision / recall;
- the flow provider's two-view triangulation of the first `--frames` frames: with the time
  neighbours from zero (the provider's choice off a wide rig) and with the two nearest other rig
  cameras from the sparse-point guide (on a wide rig). The guide reads the EVEN sparse points,
  the depth is scored at the ODD ones (median |z / z_point - 1| over confident pixels, per
  pair, then the median over pairs) next to the guide's own error there, so the figure is what
  the flow adds, not the guide copied back. Pairs with no confident pixel at a scored point count
  in "empty pairs".
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from baselines.data import load_scene  # noqa: E402
from baselines.data.initial_points import initial_point_cloud  # noqa: E402
from reflow_plugin import labels  # noqa: E402
from reflow_plugin.canonical_construction import METRIC_SOURCES  # noqa: E402
from reflow_plugin.canonical.geometry import to_camera  # noqa: E402
from reflow_plugin.canonical.providers import FlowProvider  # noqa: E402
from reflow_plugin.rig import pose_groups, viewing_angle_deg, wide_rig  # noqa: E402

MIN_CONFIDENCE = 0.5  # the static cloud's confidence floor (canonical/split.py)


def mask_scores(masks: list[np.ndarray], cameras) -> dict:
    """Coverage and, with evaluation masks on every view, pooled IoU / precision / recall."""
    out = {"coverage": float(np.mean([m.mean() for m in masks]))}
    truth = [c.extras.get("eval_mask") for c in cameras]
    if all(t is not None for t in truth):
        truth = [np.asarray(t.cpu() if hasattr(t, "cpu") else t) > 0.5 for t in truth]
        inter = sum(int((m & t).sum()) for m, t in zip(masks, truth))
        out.update(truth=float(np.mean([t.mean() for t in truth])),
                   iou=inter / max(sum(int((m | t).sum()) for m, t in zip(masks, truth)), 1),
                   precision=inter / max(sum(int(m.sum()) for m in masks), 1),
                   recall=inter / max(sum(int(t.sum()) for t in truth), 1))
    return out


def pair_errors(provider: FlowProvider, n: int, m: int, scored: np.ndarray) -> tuple[float | None, float | None]:
    """(flow depth error, guide depth error) of frame n triangulated with m at the `scored` points."""
    rows, cols = provider.grid()
    points, conf = provider.triangulate(n, m)
    depth = to_camera(points, provider.viewmats[n])[..., 2]
    cam = to_camera(scored, provider.viewmats[n])
    cam = cam[cam[:, 2] > 1e-6]
    uv = cam @ provider.K[n].T
    col = np.floor(uv[:, 0] / uv[:, 2] / provider.stride).astype(int)
    row = np.floor(uv[:, 1] / uv[:, 2] / provider.stride).astype(int)
    inside = (col >= 0) & (col < len(cols)) & (row >= 0) & (row < len(rows))
    col, row, z = col[inside], row[inside], cam[inside, 2]
    good = conf[row, col] > MIN_CONFIDENCE
    if not good.any():
        return None, None
    flow_error = float(np.median(np.abs(depth[row[good], col[good]] / z[good] - 1)))
    guide = provider.guide(n)
    if guide is None:
        return flow_error, None
    guide_rc = guide[np.ix_(rows, cols)]
    return flow_error, float(np.median(np.abs(guide_rc[row[good], col[good]] / z[good] - 1)))


def triangulation(cameras, points: np.ndarray, frames: int, by_camera: bool) -> dict:
    """Median errors over the pairs of the first `frames` frames (see the module docstring)."""
    provider = FlowProvider(cameras, stride=1, anchors=points[0::2] if by_camera else None)
    provider.rig = by_camera  # the policy under test, whatever the capture
    flow, guide, confident, empty, pairs = [], [], [], 0, 0
    for n in range(min(frames, len(cameras))):
        for m in provider.partners(n):
            pairs += 1
            error, guide_error = pair_errors(provider, n, m, points[1::2])
            confident.append(float((provider.triangulate(n, m)[1] > MIN_CONFIDENCE).mean()))
            if error is None:
                empty += 1
                continue
            flow.append(error)
            if guide_error is not None:
                guide.append(guide_error)
    return {"pairs": pairs, "empty pairs": empty, "confident": float(np.mean(confident)),
            "depth error": float(np.median(flow)) if flow else None,
            "guide error": float(np.median(guide)) if guide else None}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-s", "--source", type=Path, required=True, help="dataset folder")
    parser.add_argument("-r", "--resolution", type=int, default=4, help="train.py -r")
    parser.add_argument("--frames", type=int, default=12, help="frames whose pairs are triangulated")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args(argv)
    if not args.source.is_dir():
        print(f"rig_pairs: {args.source} is not a folder", file=sys.stderr)
        return 2
    scene = load_scene(args.source, resolution=args.resolution, eval=True)
    cameras = [c.to("cpu") for c in scene.train_cameras]
    cloud, source = initial_point_cloud(scene)  # the host's sparse points, as a run gets them
    if source not in METRIC_SOURCES or len(cloud) < 6:
        print(f"rig_pairs: {args.source} gives no sparse static points ({source} cloud); the guide needs them",
              file=sys.stderr)
        return 2
    points = np.random.default_rng(0).permutation(np.asarray(cloud.points, np.float64))  # even / odd: no order bias
    order = sorted(range(len(cameras)), key=lambda k: (cameras[k].time, cameras[k].frame_index))
    viewmats = [cameras[k].viewmat.double().numpy() for k in order]
    angles = [viewing_angle_deg(a, b) for a, b in zip(viewmats[:-1], viewmats[1:])]
    report: dict = {"frames": len(cameras), "poses": int(pose_groups(viewmats).max()) + 1,
                    "consecutive angle deg": float(np.median(angles)), "wide rig": wide_rig(viewmats)}
    print(f"rig: {report['frames']} frames, {report['poses']} camera poses, consecutive frames "
          f"{report['consecutive angle deg']:.1f} deg apart (median): wide rig {report['wide rig']}")
    start = time.perf_counter()
    by_camera = labels.estimated_masks(cameras, None)  # within each rig camera on a wide rig
    sequences = labels.pairing_sequences
    labels.pairing_sequences = lambda c: [order]  # time order, as off a wide rig
    try:
        by_time = labels.estimated_masks(cameras, None)
    finally:
        labels.pairing_sequences = sequences
    report["masks"] = {"time order": mask_scores(by_time, cameras), "by camera": mask_scores(by_camera, cameras)}
    print(f"masks ({time.perf_counter() - start:.0f} s): " + "; ".join(
        f"{name}: " + ", ".join(f"{k} {v:.3f}" for k, v in scores.items())
        for name, scores in report["masks"].items()))
    report["triangulation"] = {"time neighbours, from zero": triangulation(cameras, points, args.frames, False),
                               "nearest rig cameras, guided": triangulation(cameras, points, args.frames, True)}
    for name, figures in report["triangulation"].items():
        print(f"triangulation, {name}: " + ", ".join(
            f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in figures.items()))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
