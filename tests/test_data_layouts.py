"""Folders carrying several layouts: documented choice with a warning, poses_bounds.npy always
validated, test split repeating training views warned about."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from baselines.data import DatasetError, load_scene
from baselines.data.detection import detect_layout
from tests.data_fixtures import layouts
from tests.data_fixtures.scene import make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene(num_frames=8)


@pytest.fixture
def mixed(scene, tmp_path):
    """An NVIDIA capture also converted for D-NeRF and HyperNeRF code (files side by side)."""
    root = tmp_path / "mixed"
    layouts.write_nvidia(scene, root, disp=False, masks=False)
    layouts.write_dnerf(scene, root)
    (root / "dataset.json").write_text("{}")
    (root / "scene.json").write_text("{}")
    return root


def test_ambiguous_folder_prefers_poses_bounds_and_says_so(mixed, caplog):
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        info = load_scene(mixed, eval=True)
    assert info.dataset_type == "nvidia"
    warnings = [r.getMessage() for r in caplog.records if "several dataset layouts" in r.getMessage()]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert "picked nvidia" in warnings[0] and "poses_bounds.npy" in warnings[0]
    assert "dnerf (transforms_train.json)" in warnings[0] and "hypernerf (dataset.json + scene.json)" in warnings[0]
    assert info.metadata["layout_detection"]["also_matched"] == [
        {"type": "hypernerf", "files": "dataset.json + scene.json"},
        {"type": "dnerf", "files": "transforms_train.json"}]
    assert load_scene(mixed, dataset_type="dnerf").dataset_type == "dnerf"  # --dataset_type overrides
    # every listed --dataset_type choice has a reader ("synthetic": the simulator's NVIDIA layout)
    from arguments.params import DATASET_TYPES
    from baselines.data.loader import ALIASES, READERS
    assert all(ALIASES.get(choice, choice) in READERS for choice in DATASET_TYPES if choice != "auto")
    assert load_scene(mixed, dataset_type="synthetic").dataset_type == "nvidia"


def test_unambiguous_folder_gives_no_warning(scene, tmp_path, caplog):
    layouts.write_nvidia(scene, tmp_path / "nv", disp=False, masks=False)
    (tmp_path / "nv" / "sparse" / "0").mkdir(parents=True)  # the COLMAP model LLFF poses come from
    (tmp_path / "nv" / "sparse" / "0" / "cameras.txt").write_text("")
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        detection = detect_layout(tmp_path / "nv")
    assert detection.kind == "nvidia" and not detection.ambiguous and not caplog.records


def test_poses_bounds_is_validated_whatever_reader_runs(mixed):
    path = mixed / "poses_bounds.npy"
    original = np.load(path)
    rows = original.copy()
    rows[3, 5] = np.nan
    np.save(path, rows)
    for dataset_type in ("auto", "dnerf"):
        with pytest.raises(DatasetError, match=r"non-finite .*poses_bounds\.npy") as err:
            load_scene(mixed, dataset_type=dataset_type)
        assert "\n" not in str(err.value)
    np.save(path, original[:5])  # finite, but 5 poses for 8 images
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy has 5 poses but .*images holds 8"):
        load_scene(mixed, dataset_type="dnerf")


def test_test_split_equal_to_training_split_is_warned(scene, tmp_path, caplog):
    root = tmp_path / "d"
    layouts.write_dnerf(scene, root)
    (root / "transforms_test.json").write_text((root / "transforms_train.json").read_text())
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        info = load_scene(root, eval=True)
    messages = [r.getMessage() for r in caplog.records if "test split" in r.getMessage()]
    assert len(messages) == 1 and "identical to the training split" in messages[0]
    assert info.metadata["test_views_in_train"] == len(info.test_cameras)

    caplog.clear()
    layouts.write_dnerf(scene, tmp_path / "ok")
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        load_scene(tmp_path / "ok", eval=True)
    assert not [r for r in caplog.records if "test split" in r.getMessage()]


def test_run_config_records_the_layout_choice(mixed, tmp_path):
    from baselines.fourdgs.app import REPO_ROOT, build_trainer

    build_trainer(["-s", str(mixed), "-m", str(tmp_path / "run"), "--quiet",
                   "--configs", str(REPO_ROOT / "arguments/synthetic/default.py")])
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["_dataset_layout"]["picked"] == "nvidia"
    assert {m["type"] for m in saved["_dataset_layout"]["also_matched"]} == {"dnerf", "hypernerf"}


def test_arguments_a_reader_does_not_read_are_warned_about(mixed, caplog):
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        load_scene(mixed, dataset_type="dnerf", llffhold=4)
    assert [r.getMessage() for r in caplog.records if "not read" in r.getMessage()] == [
        "--llffhold 4 is not read by the dnerf reader (its layout fixes it)"]
    caplog.clear()
    # the warning comes before the reader runs (mixed's HyperNeRF files are empty stand-ins)
    with caplog.at_level(logging.WARNING, logger="baselines.data"), pytest.raises(DatasetError):
        load_scene(mixed, dataset_type="hypernerf", eval=False)  # HyperNeRF's own split, whatever --no-eval says
    assert [r.getMessage() for r in caplog.records if "not read" in r.getMessage()] == [
        "--no-eval is not read by the hypernerf reader (its layout fixes it)"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        load_scene(mixed, dataset_type="nvidia", llffhold=4, eval=True)  # nvidia holds out every 4th frame
    assert not [r for r in caplog.records if "not read" in r.getMessage()]
