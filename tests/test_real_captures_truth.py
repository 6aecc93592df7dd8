"""Clip captures with annotations (`Capture.truth`, the DAVIS clips): setup on a tiny fake mirror
writes evaluation-only masks matched to prepare's frame names, and the readers score with them.

prepare itself is replaced by a stand-in that writes a prepared dataset (tests/test_prepare.py
covers prepare); everything else (git archive of the pinned commit, binarising, resizing,
matching by source index) runs for real.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from baselines.data import load_scene
from benchmarks import prepare_davis, real_captures
from benchmarks.real_captures import CAPTURES, TRUTH_MASKS, Capture, CaptureError
from tests.data_fixtures import layouts
from tests.data_fixtures.scene import make_scene

FRAMES, W, H = 4, 16, 8
KEPT = ("00000.png", "00002.png", "00003.png")  # prepare registered three of the four frames


def _labels(k: int) -> np.ndarray:
    """Annotation of frame k: object 1 in the left columns 0..k, object 2 in the bottom-right corner."""
    labels = np.zeros((H, W), np.uint8)
    labels[:, : k + 1] = 1
    labels[H - 2:, W - 3:] = 2
    return labels


@pytest.fixture
def mirror(tmp_path) -> tuple[Path, str]:
    """A bare git mirror with DAVIS-style frames and annotations of one clip."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    work = tmp_path / "work"
    frames, notes = work / "DAVIS/JPEGImages/480p/clip", work / "DAVIS/Annotations/480p/clip"
    frames.mkdir(parents=True)
    notes.mkdir(parents=True)
    for k in range(FRAMES):
        cv2.imwrite(str(frames / f"{k:05d}.jpg"), np.full((H, W, 3), 40 * k, np.uint8))
        cv2.imwrite(str(notes / f"{k:05d}.png"), _labels(k))
    git = ["git", "-C", str(work), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(work)], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "data"], check=True)
    commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    bare = tmp_path / "mirror.git"
    subprocess.run(["git", "clone", "-q", "--bare", str(work), str(bare)], check=True)
    return bare, commit


def _capture(commit: str, truth: str = "DAVIS/Annotations/480p/clip") -> Capture:
    return Capture(name="davis_clip", family="clip", repo="o/r", commit=commit, folder="DAVIS/JPEGImages/480p/clip",
                   truth=truth, what="")


def _fake_prepare(calls: list):
    """subprocess.run that lets git through and replaces `python -m baselines.prepare` with a
    stand-in writing frames KEPT at half size (8x4) plus the model and report files."""
    real_run = subprocess.run

    def run(args, **kwargs):
        if args[0] != sys.executable:
            return real_run(args, **kwargs)
        calls.append(args)
        out = Path(args[args.index("-o") + 1])
        (out / "images").mkdir(parents=True)
        (out / "sparse" / "0").mkdir(parents=True)
        (out / "prepare_report.json").write_text("{}")
        for name in KEPT:
            cv2.imwrite(str(out / "images" / name), np.zeros((H // 2, W // 2, 3), np.uint8))
        return subprocess.CompletedProcess(args, 0)
    return run


def test_setup_writes_binarised_truth_masks_matched_to_prepared_frames(mirror, tmp_path, monkeypatch):
    clone, commit = mirror
    calls: list = []
    monkeypatch.setattr(real_captures.subprocess, "run", _fake_prepare(calls))
    capture, data = _capture(commit), tmp_path / "data"
    assert not real_captures.is_ready(capture, data)
    target = real_captures.setup(capture, clone, data)
    assert len(calls) == 1 and calls[0][calls[0].index("-m") + 1] == "baselines.prepare"
    written = sorted(p.name for p in (target / TRUTH_MASKS).iterdir())
    assert written == list(KEPT)
    for name in KEPT:
        mask = cv2.imread(str(target / TRUTH_MASKS / name), cv2.IMREAD_GRAYSCALE)
        expected = cv2.resize(np.where(_labels(int(Path(name).stem)) > 0, 255, 0).astype(np.uint8), (W // 2, H // 2),
                              interpolation=cv2.INTER_NEAREST)
        assert mask.shape == (H // 2, W // 2) and np.array_equal(mask, expected), name  # both objects, any id > 0
    assert real_captures.is_ready(capture, data)
    shutil.rmtree(target / TRUTH_MASKS)
    assert not real_captures.is_ready(capture, data)  # a clip with truth is not ready without its masks


def test_annotations_that_do_not_match_the_frames_stop_before_prepare(mirror, tmp_path, monkeypatch):
    clone, commit = mirror
    calls: list = []
    monkeypatch.setattr(real_captures.subprocess, "run", _fake_prepare(calls))
    with pytest.raises(CaptureError, match="failed in"):  # no such folder at that commit
        real_captures.setup(_capture(commit, truth="DAVIS/Annotations/480p/other"), clone, tmp_path / "a")
    assert calls == []


def test_colmap_reader_scores_with_the_truth_masks_not_the_training_masks(tmp_path):
    scene = make_scene(num_frames=3, width=32, height=24)
    root = tmp_path / "c"
    layouts.write_colmap(scene, root)
    (root / "motion_masks").mkdir()
    (root / TRUTH_MASKS).mkdir(parents=True)
    for k in range(3):
        auto, truth = np.zeros((24, 32), np.uint8), np.zeros((24, 32), np.uint8)
        auto[:, :8] = 255  # what a training mask estimator found
        truth[:12, :] = 255  # the annotation
        cv2.imwrite(str(root / "motion_masks" / f"{k:03d}.png"), auto)
        cv2.imwrite(str(root / TRUTH_MASKS / f"{k:03d}.png"), truth)
    loaded = load_scene(root)
    for camera in loaded.train_cameras:
        assert camera.mask[:, :8].min() == 1 and camera.mask[:, 8:].max() == 0  # training keeps its own masks
        assert camera.evaluation_mask[:12].min() == 1 and camera.evaluation_mask[12:].max() == 0


def test_registry_holds_the_thirteen_davis_clips_with_annotations():
    davis = prepare_davis.davis_captures(None)
    assert len(davis) == 13 and all(c.truth.endswith(c.folder.rsplit("/", 1)[-1]) for c in davis)
    assert CAPTURES["davis_bmx_trees"].folder == "DAVIS/JPEGImages/480p/bmx-trees"
    with pytest.raises(CaptureError, match="unknown DAVIS clip"):
        prepare_davis.davis_captures("blackswan,nope")


def test_mask_scores_pool_pixels_over_frames():
    truth = [np.zeros((4, 4), bool), np.zeros((4, 4), bool)]
    truth[0][:2] = True  # 8 pixels
    masks = [np.zeros((4, 4), bool), np.ones((4, 4), bool)]
    masks[0][:1] = True  # 4 hits in frame 0; frame 1: 16 false positives
    scores = prepare_davis.mask_scores(masks, truth)
    assert scores["precision"] == pytest.approx(4 / 20) and scores["recall"] == pytest.approx(4 / 8)
    assert scores["IoU"] == pytest.approx(4 / 24)


def test_davis_table_scores_the_masks_the_dataset_trains_with(tmp_path):
    """`prepare_davis.auto_mask_scores`: the pre-SfM `.prepare/masks/` of a dataset prepared before
    the posed stage; the dataset's `motion_masks/` once its report says `"stage": "posed"`."""
    capture = prepare_davis.davis_captures("dog")[0]
    dataset, truth = real_captures.dataset_dir(capture, tmp_path), real_captures.truth_dir(capture, tmp_path)
    for folder in (dataset / ".prepare" / "masks", dataset / "motion_masks", truth):
        folder.mkdir(parents=True)
    label = np.zeros((H, W), np.uint8)
    label[:, :8] = 1  # the left half moves
    left, right = np.where(label > 0, 255, 0).astype(np.uint8), np.where(label > 0, 0, 255).astype(np.uint8)
    for k in range(2):
        cv2.imwrite(str(truth / f"{k:05d}.png"), label)
        cv2.imwrite(str(dataset / ".prepare" / "masks" / f"{k:05d}.png"), right)  # wrong half
        cv2.imwrite(str(dataset / "motion_masks" / f"{k:05d}.png"), left)  # right half
    (dataset / "prepare_report.json").write_text(json.dumps({"masks": {"source": "auto", "mean_coverage": 0.5}}))
    assert prepare_davis.auto_mask_scores(capture, tmp_path)["IoU"] == 0.0
    (dataset / "prepare_report.json").write_text(json.dumps({"masks": {"source": "auto", "stage": "posed"}}))
    assert prepare_davis.auto_mask_scores(capture, tmp_path)["IoU"] == 1.0
