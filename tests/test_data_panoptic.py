"""The panoptic reader (Dynamic3DGaussians layout) on a tiny capture written here with known cameras.

A ring of cameras looks at a red ball moving over a grey background; seg/ holds the ball's exact
silhouettes. The reader must give back the cameras in our convention, the monocular camera cycle,
the held-out test cameras at every k-th timestamp, seg/ as evaluation-only masks, and test-view
masks (visual hull) that cover the ball's true silhouette; bad input gives one error naming the file.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from baselines.data import DatasetError, load_scene
from baselines.data.loader import detect_dataset_type
from baselines.data.panoptic import default_train_cameras, Meta, read_panoptic

WIDTH, HEIGHT, FOCAL, STEPS = 64, 48, 40.0, 6
TRAIN_IDS, TEST_IDS = [1, 2, 3, 4, 5, 6, 7, 8], [0, 9]
RADIUS = 0.5


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4,4] world->camera (OpenCV axes) at `centre` looking at `target`, world y down."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(np.array([0.0, 1.0, 0.0]), forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ centre
    return w2c


def ring_camera(angle_deg: float, height: float) -> np.ndarray:
    a = np.radians(angle_deg)
    return look_at(np.array([4.0 * np.cos(a), height, 4.0 * np.sin(a)]), np.zeros(3))


# 8 training cameras every 45 degrees (alternating heights), 2 test cameras between neighbours
ANGLES = {cid: 45.0 * i for i, cid in enumerate(TRAIN_IDS)}
ANGLES.update({0: 10.0, 9: 190.0})
K_STORED = np.array([[FOCAL, 0, WIDTH / 2 - 0.5], [0, FOCAL, HEIGHT / 2 - 0.5], [0, 0, 1]])  # integer centres


def ball_centre(t: int) -> np.ndarray:
    return np.array([0.3 * np.sin(t), 0.0, 0.3 * np.cos(t)])


def silhouette(w2c: np.ndarray, t: int) -> np.ndarray:
    """[H,W] bool: pixels (integer-centred, as the stored K) whose ray hits the ball."""
    R, trans = w2c[:3, :3], w2c[:3, 3]
    centre_cam = R @ ball_centre(t) + trans
    ys, xs = np.mgrid[0:HEIGHT, 0:WIDTH].astype(float)
    rays = np.stack([(xs - K_STORED[0, 2]) / FOCAL, (ys - K_STORED[1, 2]) / FOCAL, np.ones_like(xs)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    along = rays @ centre_cam
    miss = np.sum(centre_cam ** 2) - along ** 2
    return (along > 0) & (miss <= RADIUS ** 2)


def write_capture(root: Path, *, steps: int = STEPS) -> Path:
    def meta(ids: list[int], seg: bool) -> dict:
        out = {"w": WIDTH, "h": HEIGHT, "k": [], "w2c": [], "fn": [], "cam_id": []}
        for t in range(steps):
            out["k"].append([K_STORED.tolist()] * len(ids))
            out["w2c"].append([ring_camera(ANGLES[c], -0.8 if c % 2 else 0.8).tolist() for c in ids])
            out["fn"].append([f"{c}/{t:06d}.jpg" for c in ids])
            out["cam_id"].append(list(ids))
            for c, w2c in zip(ids, out["w2c"][-1]):
                ball = silhouette(np.array(w2c), t)
                image = np.full((HEIGHT, WIDTH, 3), 128, np.uint8)
                image[ball] = (0, 0, 230)  # BGR red
                (root / "ims" / str(c)).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / "ims" / str(c) / f"{t:06d}.png"), image)
                # the layout's names say .jpg; a lossless copy under that name keeps the test exact
                (root / "ims" / str(c) / f"{t:06d}.png").rename(root / "ims" / str(c) / f"{t:06d}.jpg")
                if seg:
                    (root / "seg" / str(c)).mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(root / "seg" / str(c) / f"{t:06d}.png"), ball.astype(np.uint8) * 255)
        return out

    root.mkdir(parents=True, exist_ok=True)
    (root / "train_meta.json").write_text(json.dumps(meta(TRAIN_IDS, seg=True)))
    (root / "test_meta.json").write_text(json.dumps(meta(TEST_IDS, seg=False)))
    return root


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return write_capture(tmp_path_factory.mktemp("panoptic"))


@pytest.fixture(scope="module")
def scene(capture):
    return load_scene(capture, eval=True, reader_options={"train_cameras": [2, 3, 4], "test_cameras": "0,9",
                                                          "test_every": 2})


def test_detected_from_its_files(capture):
    assert detect_dataset_type(capture) == "panoptic"


def test_training_cycles_one_camera_per_timestamp(scene):
    assert [c.camera_id for c in scene.train_cameras] == [2, 3, 4, 2, 3, 4]
    assert [c.frame_index for c in scene.train_cameras] == list(range(STEPS))
    assert [c.time for c in scene.train_cameras] == pytest.approx([t / (STEPS - 1) for t in range(STEPS)])
    assert scene.metadata["protocol"]["train_cameras"] == [2, 3, 4]


def test_cameras_in_our_convention(scene):
    """Stored w2c as the viewmat; K's integer pixel centres moved to +0.5."""
    for camera in scene.train_cameras + scene.test_cameras:
        expected = ring_camera(ANGLES[camera.camera_id], -0.8 if camera.camera_id % 2 else 0.8)
        np.testing.assert_allclose(camera.viewmat.numpy(), expected, atol=1e-6)
        np.testing.assert_allclose(camera.K.numpy(), K_STORED + np.array([[0, 0, .5], [0, 0, .5], [0, 0, 0]]),
                                   atol=1e-5)
        # the ball's projected centre lands on the red silhouette's centroid (our convention: +0.5)
        p = camera.viewmat.double().numpy() @ np.append(ball_centre(camera.frame_index), 1.0)
        uv = (camera.K.double().numpy() @ p[:3])[:2] / p[2]
        red = (camera.image[..., 0] > 0.6).numpy()
        ys, xs = np.nonzero(red)
        np.testing.assert_allclose([xs.mean() + 0.5, ys.mean() + 0.5], uv, atol=0.35)


def test_test_split_is_held_out_cameras_every_kth_timestamp(scene):
    got = [(c.frame_index, c.camera_id) for c in scene.test_cameras]
    assert got == [(t, c) for t in (0, 2, 4) for c in TEST_IDS]
    assert not {c.camera_id for c in scene.test_cameras} & {c.camera_id for c in scene.train_cameras}
    assert scene.metadata["protocol"]["test_timestamps"] == [0, 2, 4]


def test_seg_masks_are_for_evaluation_only(scene, capture):
    for camera in scene.train_cameras:
        assert camera.mask is None  # training never sees them by default
        seg = silhouette(ring_camera(ANGLES[camera.camera_id], -0.8 if camera.camera_id % 2 else 0.8),
                         camera.frame_index)
        np.testing.assert_array_equal(camera.evaluation_mask.numpy() > 0.5, seg)
    asked = read_panoptic(capture, eval=False, train_cameras="5", train_masks=True)
    assert asked.train_cameras[0].mask is not None and asked.test_cameras == []


def test_test_views_get_the_visual_hull_of_the_seg_masks(scene):
    for camera in scene.test_cameras:
        truth = silhouette(ring_camera(ANGLES[camera.camera_id], 0.8 if camera.camera_id % 2 == 0 else -0.8),
                           camera.frame_index)
        hull = camera.evaluation_mask.numpy() > 0.5
        iou = (hull & truth).sum() / (hull | truth).sum()
        assert truth.sum() > 20 and iou > 0.6, (camera.image_name, iou)
        assert (hull & truth).sum() / truth.sum() > 0.9  # the ball is covered


def test_default_is_a_sweep_of_the_cameras_nearest_the_first_test_camera(capture):
    train, test = Meta(capture / "train_meta.json"), Meta(capture / "test_meta.json")
    centres = {c: np.linalg.inv(ring_camera(ANGLES[c], -0.8 if c % 2 else 0.8))[:3, 3] for c in TRAIN_IDS + TEST_IDS}
    nearest = sorted(TRAIN_IDS, key=lambda c: np.linalg.norm(centres[c] - centres[0]))[:5]
    chosen = default_train_cameras(train, test)
    assert sorted(chosen) == sorted(nearest)
    # a sweep around the ring (angles relative to test camera 0 at 10 degrees), one way or the other
    angles = [(ANGLES[c] - 10.0 + 180.0) % 360.0 - 180.0 for c in chosen]
    assert angles == sorted(angles) or angles == sorted(angles, reverse=True)
    info = load_scene(capture, eval=True)
    assert info.metadata["protocol"]["train_cameras"] == chosen
    assert {c.camera_id for c in info.test_cameras} == {0}


def _edited(src: Path, dst: Path, name: str, edit) -> Path:
    import shutil

    shutil.copytree(src, dst)
    data = json.loads((dst / name).read_text())
    edit(data)
    (dst / name).write_text(json.dumps(data))
    return dst


@pytest.mark.parametrize("name, edit, culprit", [
    ("train_meta.json", lambda d: d["fn"][2].pop(), "'fn'[2] has 7 cameras"),
    ("train_meta.json", lambda d: d["w2c"].pop(), "per-timestamp lists differ in length"),
    ("train_meta.json", lambda d: d["w2c"][1][3][0].__setitem__(0, float("nan")), "non-finite 'w2c' value"),
    ("test_meta.json", lambda d: d.pop("k"), "missing key 'k'"),
    ("train_meta.json", lambda d: d["cam_id"][3].reverse(), "'cam_id'[3] lists the cameras in another order"),
])
def test_bad_meta_gives_one_error_naming_the_file(capture, tmp_path, name, edit, culprit):
    source = _edited(capture, tmp_path / "bad", name, edit)
    with pytest.raises(DatasetError) as err:
        load_scene(source, eval=True)
    assert str(source / name) in str(err.value) and culprit in str(err.value)


def test_missing_meta_file_is_named(capture, tmp_path):
    import shutil

    source = tmp_path / "no_test"
    shutil.copytree(capture, source)
    (source / "test_meta.json").unlink()
    with pytest.raises(DatasetError, match="missing JSON file: .*test_meta.json"):
        load_scene(source, eval=True, reader_options={"train_cameras": [1]})
    (source / "train_meta.json").unlink()
    with pytest.raises(DatasetError, match="train_meta.json"):
        load_scene(source, dataset_type="panoptic")


def test_bad_options_are_named(capture):
    with pytest.raises(DatasetError, match="train_cameras \\[42\\]"):
        load_scene(capture, reader_options={"train_cameras": "1,42"})
    with pytest.raises(DatasetError, match="test_cameras \\[3\\] are not cameras of .*test_meta.json"):
        load_scene(capture, eval=True, reader_options={"test_cameras": "3"})
    with pytest.raises(DatasetError, match="test_every=0"):
        load_scene(capture, reader_options={"test_every": 0})


def test_train_flags_reach_the_reader_and_the_run_records_the_protocol(capture, tmp_path):
    from baselines.fourdgs.app import REPO_ROOT, build_trainer

    trainer = build_trainer(["-s", str(capture), "-m", str(tmp_path / "run"), "--quiet", "--train_cameras", "3,4",
                             "--test_cameras", "9", "--test_every", "3", "--configs", str(REPO_ROOT / "arguments/synthetic/default.py")])
    assert [c.camera_id for c in trainer.train_cameras] == [3, 4, 3, 4, 3, 4]
    assert [(c.camera_id, c.frame_index) for c in trainer.test_cameras] == [(9, 0), (9, 3)]
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["_protocol"]["train_cameras"] == [3, 4] and saved["_protocol"]["test_timestamps"] == [0, 3]
    assert saved["_protocol"]["test_cameras"] == [9]
