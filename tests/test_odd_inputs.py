"""Odd inputs that used to pass silently (issue 25, items 4-8, 10, 12); the command-line side of
these (and items 11, 13) is in test_bad_inputs.py."""
from __future__ import annotations

import json
import logging
import shutil
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from baselines.data import DatasetError, load_scene
from baselines.data.colmap import read_times
from baselines.data.resolution import check_target_size
from baselines.data.views import ViewSpec, load_views
from baselines.fourdgs.checkpoint import load_training_state


def test_resolution_needing_more_memory_or_below_a_few_pixels_is_refused(caplog):
    with pytest.raises(DatasetError, match=r"-r/--resolution 100000 makes the 12 images of x 100000x75000 px "
                                           r"\(a target width.*GiB to hold them, 1.0 GiB available"):
        check_target_size((640, 480), 100000, 12, "x", memory=2**30)
    with pytest.raises(DatasetError, match=r"makes the 32x24 images of x 3x2 px.*at least 4 px a side"):
        check_target_size((32, 24), 3, 12, "x", memory=2**30)
    with caplog.at_level(logging.INFO, logger="baselines.data.resolution"):
        assert check_target_size((64, 48), 2, 12, "x", memory=2**30) == (32, 24)
    assert "views: 32x24 px, downscaled from 64x48 (-r 2)" in caplog.text


@pytest.mark.parametrize("folder", ["disp", "motion_masks"])
def test_a_transposed_mask_or_disparity_map_is_refused(tiny_scene, tmp_path, folder):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    first = sorted((scene / folder).iterdir())[0]
    if folder == "disp":
        np.save(first, np.pad(np.load(first), ((0, 16), (0, 0))).T.copy())
    else:
        cv2.imwrite(str(first), np.ascontiguousarray(np.pad(cv2.imread(str(first), cv2.IMREAD_UNCHANGED),
                                                            ((0, 16), (0, 0))).T))
    what = "disparity map" if folder == "disp" else "motion mask"
    with pytest.raises(DatasetError, match=f"{what} .*{first.name} is 48x32 but its image is 32x32: not a scaled copy"):
        load_scene(scene)
    # a scaled copy (half size) is still accepted and resized
    if folder == "motion_masks":
        small = cv2.resize(cv2.imread(str(sorted((tiny_scene / folder).iterdir())[0]), cv2.IMREAD_UNCHANGED), (16, 16),
                           interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(first), small)
        assert load_scene(scene).train_cameras[0].mask.shape == (32, 32)


def test_shared_or_backwards_times_are_named(tmp_path, caplog):
    names = ["a", "b", "c", "d"]
    (tmp_path / "times.json").write_text(json.dumps({"times": {"a": 0.0, "b": 0.5, "c": 0.5, "d": 0.25}}))
    with caplog.at_level(logging.WARNING):
        assert read_times(tmp_path, names) == [0.0, 0.5, 0.5, 0.25]
    text = caplog.text
    assert "1 frame(s) share a time: b/c (0.5)" in text and "1 step(s) go back in time in image order: c (0.5) -> d (0.25)" in text
    caplog.clear()
    (tmp_path / "times.json").write_text(json.dumps({"times": {"a": 0.0, "b": 0.2, "c": 0.6, "d": 1.0}}))
    with caplog.at_level(logging.WARNING):
        read_times(tmp_path, names)
    assert caplog.text == ""


def test_all_black_masks_are_recorded_as_such(caplog):
    from reflow_plugin.labels import EMPTY_DATASET_MASKS, training_masks

    cameras = [SimpleNamespace(mask=torch.zeros(8, 8)) for _ in range(3)]
    with caplog.at_level(logging.WARNING):
        masks, source = training_masks(cameras, "auto", None)
    assert source == EMPTY_DATASET_MASKS and len(masks) == 3
    assert "mark no moving pixel in any of the 3 training views" in caplog.text
    cameras[1].mask[2:4, 2:4] = 1.0
    assert training_masks(cameras, "auto", None)[1] == "dataset"


def test_a_fully_transparent_frame_is_named(tmp_path, caplog):
    specs = []
    for i, alpha in enumerate((255, 0, 128)):
        rgba = np.zeros((8, 8, 4), np.uint8)
        rgba[..., :3], rgba[..., 3] = 90, alpha
        path = tmp_path / f"r_{i:03d}.png"
        cv2.imwrite(str(path), rgba)
        specs.append(ViewSpec(image_path=path, image_name=path.stem, K=np.diag([8.0, 8.0, 1.0]), calibrated_size=(8, 8),
                              viewmat=np.eye(4), time=i / 2, frame_index=i))
    with caplog.at_level(logging.WARNING):
        cameras = load_views(specs, 1, (1.0, 1.0, 1.0))
    assert "1 image(s) fully transparent (alpha 0 everywhere): they train as plain background: r_001" in caplog.text
    assert torch.equal(cameras[1].image, torch.ones(8, 8, 3))


def test_garbage_checkpoint_and_text_npy_give_one_line(tmp_path):
    junk = tmp_path / "junk.pth"
    junk.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(ValueError) as caught:
        load_training_state(junk)
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"{junk}: cannot be read as a torch file")
    assert "weights_only" not in message  # torch's page of advice is not repeated
    from baselines.data.validation import load_npy

    text = tmp_path / "poses_bounds.npy"
    text.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(DatasetError, match=r"poses_bounds.npy is not a .npy file \(no NumPy header; it starts with '1 2 3"):
        load_npy(text)


def test_canonical_alignment_writes_no_progress_bar_into_a_log(tiny_scene, capsys):
    """Off a terminal the alignment's bar stays silent (the training bar's rule); it redrew on every
    step before (set_postfix ignores mininterval): ~300 carriage returns per clip in a log file."""
    from reflow_plugin.canonical import CanonicalOptions, make_provider
    from reflow_plugin.canonical.alignment import align_frames

    cameras = load_scene(tiny_scene, eval=False).train_cameras[:4]
    provider = make_provider(cameras, tiny_scene, CanonicalOptions(depth_source="gt", max_side=16))
    h, w = (len(a) for a in provider.grid())
    frames = list(range(4))
    align_frames(provider, frames, [(0, 1), (1, 2), (2, 3)], {n: np.ones((h, w)) for n in frames}, iterations=40,
                 progress=True)
    err = capsys.readouterr().err
    assert err.count("\r") == 0 and "align" not in err
