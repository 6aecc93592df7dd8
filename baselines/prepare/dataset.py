"""Stage 4: write the dataset our COLMAP reader loads (`baselines/data/colmap.py`).

    <out>/images/NNNNN.png        registered frames only (NNNNN = source frame index)
    <out>/sparse/0/               cameras.bin, images.bin, points3D.bin (registered frames only)
    <out>/times.json              {"times": {"NNNNN.png": t}}: t in [0, 1] by source frame index,
                                  so dropping a frame leaves the others' times unchanged
    <out>/motion_masks/NNNNN.png  255 = moving (when masks were used)

SfM fixes the scene only up to scale (COLMAP spreads the cameras over about 10 units). The model
is rescaled so that the median depth of its points, seen from the registered cameras, is
`MEDIAN_DEPTH` units: the scale of the simulator's scenes, on which the training configs were
tuned (ReFlow's training diverged to NaN on an unscaled model whose median depth was about 30).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ..data.colmap_compat import image_cam_from_world

OUTPUTS = ("images", "sparse", "motion_masks", "times.json")
MEDIAN_DEPTH = 5.0


def median_point_depth(model) -> float:
    """Median z of the model's points in the frames of its registered cameras (points in front only)."""
    points = np.array([p.xyz for p in model.points3D.values()], np.float64).reshape(-1, 3)
    depths = []
    for image in model.images.values():
        if image.has_pose:
            z = (points @ image_cam_from_world(image)[:, :3].T + image_cam_from_world(image)[:, 3])[:, 2]
            depths.append(z[z > 0])
    found = np.concatenate(depths) if depths else np.zeros(0)
    return float(np.median(found)) if len(found) else 1.0


def rescale(model, median_depth: float = MEDIAN_DEPTH) -> float:
    """Scale `model` in place (about the origin) to the given median point depth; returns the factor."""
    import pycolmap

    factor = median_depth / max(median_point_depth(model), 1e-12)
    model.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), np.zeros(3)))
    return factor


def frame_times(names: Sequence[str]) -> dict[str, float]:
    """Time of each extracted frame: (index - first) / (last - first), by source frame index."""
    indices = [int(Path(n).stem) for n in names]
    first, last = min(indices), max(indices)
    span = max(last - first, 1)
    return {name: (index - first) / span for name, index in zip(names, indices)}


def clear_outputs(out: Path) -> None:
    """Remove what an earlier run wrote (never anything else)."""
    for name in OUTPUTS:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def write_dataset(out: Path, model, frame_dir: Path, registered: Sequence[str], times: dict[str, float],
                  masks: dict[str, np.ndarray] | None) -> None:
    """Write the layout above for the `registered` frame names of `model` (a pycolmap Reconstruction)."""
    clear_outputs(out)
    (out / "images").mkdir(parents=True)
    for name in registered:
        shutil.copyfile(frame_dir / name, out / "images" / name)
    model_dir = out / "sparse" / "0"
    model_dir.mkdir(parents=True)
    model.write(str(model_dir))
    (out / "times.json").write_text(json.dumps(
        {"note": "time of each image in [0, 1], by source frame index (written by baselines.prepare)",
         "times": {name: round(times[name], 8) for name in registered}}, indent=1))
    if masks is not None:
        (out / "motion_masks").mkdir()
        for name in registered:
            cv2.imwrite(str(out / "motion_masks" / name), np.where(masks[name], 255, 0).astype(np.uint8))
