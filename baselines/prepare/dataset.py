"""Stage 4: write the dataset our COLMAP reader loads (`baselines/data/colmap.py`).

    <out>/images/NNNNN.png        registered frames only (NNNNN = source frame index)
    <out>/sparse/0/               cameras.bin, images.bin, points3D.bin (registered frames only)
    <out>/times.json              {"times": {"NNNNN.png": t}}: t in [0, 1] by source frame index,
                                  so dropping a frame leaves the others' times unchanged
    <out>/motion_masks/NNNNN.png  255 = moving (when masks were used)
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

OUTPUTS = ("images", "sparse", "motion_masks", "times.json")


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
