"""scripts/error_by_region.py: distance bands around the motion mask and the per-band comparison."""
from __future__ import annotations

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "error_by_region.py"


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("error_by_region", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_region_labels_follow_the_distance_to_the_mask(tool):
    mask = np.zeros((9, 40), bool)
    mask[:, :4] = True                                    # a vertical band at the left
    labels = tool.region_labels(mask)
    assert (labels[:, :4] == 0).all()
    # column c (c >= 4) is c - 3 px from the nearest mask pixel: bands (0,2], (2,5], (5,10], (10,20], > 20
    expected = {4: 1, 5: 1, 6: 2, 8: 2, 9: 3, 13: 3, 14: 4, 23: 4, 24: 5, 39: 5}
    for column, band in expected.items():
        assert (labels[:, column] == band).all(), (column, labels[0, column])
    assert (tool.region_labels(np.zeros((4, 4), bool)) == len(tool.BANDS_PX) + 1).all()


def _write_run(folder: Path, renders: list[np.ndarray], gts: list[np.ndarray], split: str = "test") -> None:
    for sub, images in (("renders", renders), ("gt", gts)):
        (folder / split / "ours_100" / sub).mkdir(parents=True)
        for k, image in enumerate(images):
            cv2.imwrite(str(folder / split / "ours_100" / sub / f"{k:05d}.png"), image[..., ::-1])


def test_a_change_far_from_the_mask_is_attributed_to_the_far_band(tool, tmp_path, monkeypatch):
    gt = np.full((30, 40, 3), 128, np.uint8)
    mask = np.zeros((30, 40), bool)
    mask[:, :4] = True
    worse = gt.copy()
    worse[:, 30:] += 20                                   # only pixels > 20 px from the mask get worse
    _write_run(tmp_path / "a", [gt.copy()], [gt])
    _write_run(tmp_path / "b", [worse], [gt])
    scene = SimpleNamespace(test_cameras=[SimpleNamespace(evaluation_mask=torch.from_numpy(mask).float())])
    monkeypatch.setattr(tool, "load_scene", lambda source, eval: scene)
    table = tool.compare(tmp_path / "a", tmp_path / "b", tmp_path, None)
    far = next(line for line in table.splitlines() if line.startswith("| > 20 px"))
    assert far.endswith("| 100% |")
    near = next(line for line in table.splitlines() if line.startswith("| 2-5 px"))
    assert "| +0.00 | 0% |" in near
    with pytest.raises(SystemExit, match="view counts differ"):
        monkeypatch.setattr(tool, "load_scene", lambda source, eval: SimpleNamespace(test_cameras=[]))
        tool.compare(tmp_path / "a", tmp_path / "b", tmp_path, None)


def test_the_training_views_are_compared_with_the_training_cameras_masks(tool, tmp_path, monkeypatch):
    gt = np.full((30, 40, 3), 128, np.uint8)
    mask = np.zeros((30, 40), bool)
    mask[:, :4] = True
    worse = gt.copy()
    worse[:, :4] += 20                                    # worse inside the mask only
    _write_run(tmp_path / "a", [gt.copy()], [gt], split="train")
    _write_run(tmp_path / "b", [worse], [gt], split="train")
    scene = SimpleNamespace(train_cameras=[SimpleNamespace(evaluation_mask=torch.from_numpy(mask).float())],
                            test_cameras=[])
    monkeypatch.setattr(tool, "load_scene", lambda source, eval: scene)
    table = tool.compare(tmp_path / "a", tmp_path / "b", tmp_path, None, split="train")
    assert "1 train views" in table
    inside = next(line for line in table.splitlines() if line.startswith("| inside the mask"))
    assert float(inside.split("|")[5]) < -10  # B - A: B is worse inside the training views' mask
    with pytest.raises(SystemExit, match="no test/ours_N folder"):
        tool.compare(tmp_path / "a", tmp_path / "b", tmp_path, None)  # no held-out renders in these runs
