"""Exported 3D tracks against a dataset's ground-truth optical flow (the simulator's `gt/`).

    python -m baselines.export.track_eval TRACKS.npz -s data/synthetic/skating [--split test]
    errors = track_flow_errors(tracks, source_path, split="test")

For every view of the split at frame f whose next frame f + 1 is also among the tracks' views
(`view_*` keys), each track is projected at its time-f position into camera f (p_f) and at its
time-(f+1) position into camera f + 1 (p_f+1): its 2D motion p_f+1 - p_f is what the
ground-truth flow `gt/flow_fwd/<f>.npy` says the surface point at p_f does (camera motion
included). A track counts at (f, f + 1) when it is visible at both times (npz `visible`), in
front of both cameras, inside image f, and IS the surface seen at p_f: its depth in camera f
agrees with `gt/depth/<f>.npy` at that pixel within `depth_tolerance` (relative; a Gaussian
behind the skater carries the background's motion, not the skater's), the pixel is not occluded
at f + 1 (`gt/occ_fwd`), and (region "dynamic", the default) lies inside the motion mask
(`motion_masks/<f>.png`). The flow is read at the pixel p_f falls in (nearest centre: no mixing
across silhouettes). End-point error = |(p_f+1 - p_f) - flow(p_f)| in pixels.

`zero_motion` is the same statistic for tracks that would not move in 3D (only the camera's
motion): the error a track must beat to say anything about the object's motion.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from .tracks import Tracks, load_tracks, project_points

NEAR = 0.01  # the rasterizer's near plane


def _read_gt(source: Path, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None] | None:
    """(flow [H, W, 2], occluded [H, W], depth [H, W], dynamic mask [H, W] or None) of a frame, or None."""
    flow_path = source / "gt" / "flow_fwd" / f"{frame:03d}.npy"
    depth_path = source / "gt" / "depth" / f"{frame:03d}.npy"
    if not (flow_path.is_file() and depth_path.is_file()):
        return None
    flow = np.load(flow_path).astype(np.float64)
    depth = np.load(depth_path).astype(np.float64)
    occ_path = source / "gt" / "occ_fwd" / f"{frame:03d}.png"
    occluded = (cv2.imread(str(occ_path), cv2.IMREAD_GRAYSCALE) > 127) if occ_path.is_file() else np.zeros(depth.shape, bool)
    mask_path = source / "motion_masks" / f"{frame:03d}.png"
    mask = (cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) > 127) if mask_path.is_file() else None
    return flow, occluded, depth, mask


def pair_errors(tracks: Tracks, a: int, b: int, gt: tuple, region: str = "dynamic",
                depth_tolerance: float = 0.05) -> dict[str, np.ndarray]:
    """Per-track errors of view pair (a, b) (indices into the tracks' views): {"epe", "zero_motion",
    "rows"} over the tracks that count (see the module docstring)."""
    flow, occluded, depth, mask = gt
    ka, kb = tracks.at_time(tracks.view_time[a]), tracks.at_time(tracks.view_time[b])
    xy_a, z_a = project_points(tracks.positions[ka], tracks.view_K[a], tracks.view_viewmat[a])
    xy_b, z_b = project_points(tracks.positions[kb], tracks.view_K[b], tracks.view_viewmat[b])
    still_b, still_z = project_points(tracks.positions[ka], tracks.view_K[b], tracks.view_viewmat[b])
    w, h = (int(v) for v in tracks.view_size[a])
    gh, gw = depth.shape
    sx, sy = gw / w, gh / h  # ground truth stored at another resolution: sample and scale
    ok = tracks.visible[ka] & tracks.visible[kb] & (z_a > NEAR) & (z_b > NEAR) & (still_z > NEAR)
    ok &= np.isfinite(xy_a).all(1) & np.isfinite(xy_b).all(1)
    ok &= (xy_a[:, 0] >= 0) & (xy_a[:, 0] < w) & (xy_a[:, 1] >= 0) & (xy_a[:, 1] < h)
    rows = np.flatnonzero(ok)
    col = np.clip((xy_a[rows, 0] * sx).astype(np.int64), 0, gw - 1)
    row = np.clip((xy_a[rows, 1] * sy).astype(np.int64), 0, gh - 1)
    keep = ~occluded[row, col] & (np.abs(z_a[rows] - depth[row, col]) <= depth_tolerance * depth[row, col])
    if region == "dynamic" and mask is not None:
        keep &= mask[row, col]
    rows, row, col = rows[keep], row[keep], col[keep]
    truth = flow[row, col] / np.array([sx, sy])
    moved = xy_b[rows] - xy_a[rows]
    camera_only = still_b[rows] - xy_a[rows]
    return {"epe": np.linalg.norm(moved - truth, axis=1), "zero_motion": np.linalg.norm(camera_only - truth, axis=1),
            "rows": rows}


def track_flow_errors(tracks: Tracks, source_path: str | Path, split: str = "test", region: str = "dynamic",
                      depth_tolerance: float = 0.05) -> dict:
    """Median / mean EPE of the tracks over the split's view pairs (see the module docstring).

    Returns {"available": bool, "reason"?, "pairs": [{frame, tracks, median_epe, ...}], "tracks",
    "median_epe", "mean_epe", "median_zero_motion", "distinct_tracks"}.
    """
    source = Path(source_path)
    if split not in ("test", "train", "all"):
        raise ValueError(f"split must be test, train or all, got {split!r}")
    if len(tracks.view_frame) == 0:
        raise ValueError("the tracks file holds no cameras (view_* keys): export it with python -m baselines.export")
    by_frame = {int(f): i for i, f in enumerate(tracks.view_frame)}
    pairs, epe, zero, used = [], [], [], set()
    for i, frame in enumerate(tracks.view_frame):
        if split != "all" and bool(tracks.view_test[i]) != (split == "test"):
            continue
        j = by_frame.get(int(frame) + 1)
        gt = _read_gt(source, int(frame)) if j is not None else None
        if gt is None:
            continue
        result = pair_errors(tracks, i, j, gt, region, depth_tolerance)
        n = len(result["epe"])
        pairs.append({"frame": int(frame), "tracks": n,
                      "median_epe": float(np.median(result["epe"])) if n else None,
                      "median_zero_motion": float(np.median(result["zero_motion"])) if n else None})
        epe.append(result["epe"])
        zero.append(result["zero_motion"])
        used.update(int(r) for r in result["rows"])
    if not pairs:
        return {"available": False, "reason": f"no {split} view with a next frame and ground truth under {source / 'gt'}"}
    epe_all, zero_all = np.concatenate(epe), np.concatenate(zero)
    count = len(epe_all)
    return {"available": True, "split": split, "region": region, "pairs": pairs, "tracks": count,
            "distinct_tracks": len(used),
            "median_epe": float(np.median(epe_all)) if count else None,
            "mean_epe": float(np.mean(epe_all)) if count else None,
            "median_zero_motion": float(np.median(zero_all)) if count else None}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m baselines.export.track_eval", description=__doc__.split("\n\n")[0])
    parser.add_argument("tracks", type=Path, help="tracks.npz from python -m baselines.export --format tracks")
    parser.add_argument("-s", "--source_path", type=Path, required=True, help="the dataset (with gt/flow_fwd, gt/depth)")
    parser.add_argument("--split", default="test", choices=("test", "train", "all"))
    parser.add_argument("--region", default="dynamic", choices=("dynamic", "all"))
    parser.add_argument("--depth_tolerance", type=float, default=0.05)
    args = parser.parse_args(argv)
    result = track_flow_errors(load_tracks(args.tracks), args.source_path, args.split, args.region, args.depth_tolerance)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    from baselines.fourdgs.app import run_cli

    run_cli(lambda: main(sys.argv[1:]))
