"""Flow evaluation of ANY trained model (4DGS baseline or ReFlow) against ground-truth flow.

    python -m reflow_plugin.evaluate -m output/skating [--iteration N] [--images 4]

For every pair of consecutive frames (f, f + 1) of the dataset (training and test frames alike,
reported separately by the split of frame f), the model's full flow f -> f+1 is rendered exactly
as training renders it (one pass, DESIGN.md section 5) and compared with the dataset's ground
truth (the simulator's `gt/flow_fwd/<f>.npy`, occlusions `gt/occ_fwd/<f>.png`): end-point error
on pixels that are not occluded and where the rendered flow is valid, overall and inside /
outside the motion mask. `coverage` is the share of non-occluded pixels with a valid rendered
flow. Writes `<model>/flow_metrics.json` and, with `--images`, flow pictures (colour wheel,
prediction | ground truth) under `<model>/flow/ours_<iter>/`. A dataset without ground-truth flow
gets no metrics (the file says why).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch

from baselines.data import Camera
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.renderer import composite_view, prepare_view

from .flow import flow_features, full_flow
from .matching import FLOW_KEY
from .visualize import flow_to_color

log = logging.getLogger(__name__)
FLOW_METRICS_FILE = "flow_metrics.json"


@torch.no_grad()
def render_full_flow(model: GaussianModel, camera_a: Camera, camera_b: Camera, stage: str = "fine",
                     backend: str = "auto", min_alpha: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(flow [H, W, 2], valid [H, W] bool) of view a towards view b (numpy)."""
    view_a = prepare_view(model, camera_a, stage, backend)
    view_b = prepare_view(model, camera_b, stage, backend)
    features = {FLOW_KEY: flow_features(view_a.projection, view_b.projection)}
    composite_view(view_a, view_a.colors.new_zeros(3), features, backend)
    flow, valid = full_flow(view_a.extras[FLOW_KEY], view_a.alpha, min_alpha)
    return flow.cpu().numpy(), valid.cpu().numpy()


def ground_truth_flow(source_path: Path, frame: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(flow [H, W, 2], occluded [H, W] bool) of frame -> frame + 1 at the given size, or None.

    Ground truth stored at another resolution is resized and its vectors scaled.
    """
    flow_path = Path(source_path) / "gt" / "flow_fwd" / f"{frame:03d}.npy"
    occ_path = Path(source_path) / "gt" / "occ_fwd" / f"{frame:03d}.png"
    if not flow_path.is_file():
        return None
    flow = np.load(flow_path).astype(np.float32)
    occluded = (cv2.imread(str(occ_path), cv2.IMREAD_GRAYSCALE) > 127) if occ_path.is_file() else np.zeros(flow.shape[:2], bool)
    h, w = flow.shape[:2]
    if (w, h) != (width, height):
        flow = cv2.resize(flow, (width, height), interpolation=cv2.INTER_LINEAR) * np.array([width / w, height / h], np.float32)
        occluded = cv2.resize(occluded.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0
    return flow, occluded


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def flow_metrics(model: GaussianModel, train_cameras: Sequence[Camera], test_cameras: Sequence[Camera],
                 source_path: Path, backend: str = "auto", image_dir: Path | None = None,
                 images: int = 0) -> dict:
    """EPE of the model's full flow against ground truth (see the module docstring)."""
    split_of = {c.frame_index: "train" for c in train_cameras}
    split_of.update({c.frame_index: "test" for c in test_cameras})
    by_frame = {c.frame_index: c for c in [*train_cameras, *test_cameras]}
    pairs, written = [], 0
    for frame in sorted(by_frame):
        if frame + 1 not in by_frame:
            continue
        cam_a, cam_b = by_frame[frame], by_frame[frame + 1]
        truth = ground_truth_flow(source_path, frame, cam_a.width, cam_a.height)
        if truth is None:
            continue
        gt, occluded = truth
        flow, valid = render_full_flow(model, cam_a, cam_b, backend=backend)
        error = np.linalg.norm(flow - gt, axis=-1)
        usable = ~occluded & valid
        row = {"frame": frame, "split": split_of[frame], "coverage": float(usable.sum() / max((~occluded).sum(), 1)),
               "epe": float(error[usable].mean()) if usable.any() else None}
        if cam_a.evaluation_mask is not None:
            dynamic = cam_a.evaluation_mask.cpu().numpy() > 0.5
            for name, region in (("epe_dynamic", dynamic), ("epe_static", ~dynamic)):
                sel = usable & region
                row[name] = float(error[sel].mean()) if sel.any() else None
        pairs.append(row)
        if image_dir is not None and written < images:
            scale = float(np.linalg.norm(gt[~occluded], axis=-1).max()) if (~occluded).any() else None
            picture = np.concatenate([flow_to_color(flow, scale, valid), flow_to_color(gt, scale, ~occluded)], axis=1)
            image_dir.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(image_dir / f"{frame:05d}.png"), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
            written += 1
    if not pairs:
        return {"available": False, "reason": f"no ground-truth flow under {Path(source_path) / 'gt' / 'flow_fwd'}"}
    summary: dict = {"available": True, "pairs": pairs}
    for split in ("train", "test"):
        rows = [r for r in pairs if r["split"] == split]
        summary[split] = {key: _mean([r[key] for r in rows if r.get(key) is not None])
                          for key in ("epe", "epe_dynamic", "epe_static", "coverage")}
        summary[split]["pairs"] = len(rows)
    return summary


def write_flow_metrics(model_path: Path, method: str, metrics: dict) -> Path:
    """Merge `metrics` under `method` into <model>/flow_metrics.json (atomic)."""
    path = Path(model_path) / FLOW_METRICS_FILE
    data = json.loads(path.read_text()) if path.is_file() else {}
    data[method] = metrics
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)
    return path


def summary_line(metrics: dict) -> str:
    if not metrics.get("available"):
        return f"flow: not evaluated ({metrics.get('reason')})"
    parts = []
    for split in ("train", "test"):
        s = metrics[split]
        if s["pairs"]:
            dyn = f", dynamic {s['epe_dynamic']:.3f}" if s.get("epe_dynamic") is not None else ""
            parts.append(f"{split} EPE {s['epe']:.3f} px{dyn} ({s['pairs']} pairs, coverage {s['coverage']:.2f})")
    return "flow: " + "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    """CLI: flow metrics of a trained model directory (render.py's -m/--iteration flags)."""
    from baselines.fourdgs.app import load_run

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m reflow_plugin.evaluate", add_help=True)
    parser.add_argument("--images", type=int, default=4, help="flow pictures to write (0 = none)")
    own, rest = parser.parse_known_args(argv)
    if own.images < 0:
        parser.error(f"--images must be >= 0 (0 = none), got {own.images}")
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    loaded = load_run(rest)
    trainer = loaded.trainer
    method = f"ours_{loaded.iteration}"
    metrics = flow_metrics(trainer.ctx.model, trainer.train_cameras, trainer.test_cameras,
                           Path(trainer.ctx.scene.source_path), loaded.args.pipe.backend,
                           trainer.ctx.model_path / "flow" / method, own.images)
    path = write_flow_metrics(trainer.ctx.model_path, method, metrics)
    print(f"[evaluate] {summary_line(metrics)} -> {path}")
    trainer.run_log.close()
    return 0


if __name__ == "__main__":
    from baselines.fourdgs.app import run_cli

    run_cli(main)
