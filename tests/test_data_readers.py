"""Readers recover the known cameras, times, splits and resolutions of generated fixtures."""
from __future__ import annotations

import json
import logging

import cv2
import numpy as np
import pytest
import torch

from baselines.data import Camera, load_scene
from baselines.data.loader import detect_dataset_type
from baselines.data.resolution import target_size
from tests.data_fixtures import layouts
from tests.data_fixtures.scene import MARKER_POINT, make_marker_scene, make_scene

WRITERS = {"nvidia": layouts.write_nvidia, "dnerf": layouts.write_dnerf,
           "hypernerf": layouts.write_hypernerf, "colmap": layouts.write_colmap}

# The fixture writer returns HyperNeRF ground truth in the normalised (Nerfies) frame.
NORMALISED = {"hypernerf": {"reader_options": {"apply_scene_transform": True}}}


@pytest.fixture(scope="module")
def scene():
    return make_scene(num_frames=8)


def all_cameras(info) -> list[Camera]:
    return sorted(info.train_cameras + info.test_cameras, key=lambda c: (c.frame_index, c.camera_id))


def project(camera: Camera, point: np.ndarray) -> np.ndarray:
    p = camera.viewmat.double().numpy() @ np.append(point, 1.0)
    uvw = camera.K.double().numpy() @ p[:3]
    return uvw[:2] / uvw[2]


def intensity_centroid(image: torch.Tensor) -> np.ndarray:
    """(x, y) centroid with pixel (i, j) centred at (j + 0.5, i + 0.5)."""
    weight = image.double().numpy().sum(axis=2)
    rows, cols = np.indices(weight.shape)
    return np.array([(weight * (cols + 0.5)).sum(), (weight * (rows + 0.5)).sum()]) / weight.sum()


@pytest.mark.parametrize("layout", list(WRITERS))
def test_reader_recovers_cameras_exactly(layout, scene, tmp_path):
    gt = WRITERS[layout](scene, tmp_path / layout)
    info = load_scene(tmp_path / layout, resolution=1 if layout == "hypernerf" else -1, **NORMALISED.get(layout, {}))
    assert info.dataset_type == layout == detect_dataset_type(tmp_path / layout)
    cams = all_cameras(info)
    frames = [c.frame_index for c in cams]
    for cam, frame in zip(cams, frames):
        np.testing.assert_allclose(cam.viewmat.numpy(), gt["viewmats"][frame], atol=1e-5)
        np.testing.assert_allclose(cam.K.numpy(), gt["K"], atol=1e-5)
        assert (cam.width, cam.height) == (scene.width, scene.height)
        assert cam.image.shape == (scene.height, scene.width, 3) and cam.image.dtype == torch.float32
        np.testing.assert_allclose(cam.camera_center.numpy(), np.linalg.inv(gt["viewmats"][frame])[:3, 3], atol=1e-5)


@pytest.mark.parametrize("layout", list(WRITERS))
def test_marker_projects_to_its_pixel_centroid(layout, tmp_path):
    """Independent check of axes and the +0.5 pixel-centre convention from raw pixels: a tiny
    white square at a known 3D point must appear where the loaded camera projects it."""
    marker = make_marker_scene()
    WRITERS[layout](marker, tmp_path / layout)
    info = load_scene(tmp_path / layout, resolution=1, **NORMALISED.get(layout, {}))
    point = MARKER_POINT
    if layout == "hypernerf":  # the reader maps the world by (p - center) * scale
        point = (MARKER_POINT - layouts.HYPER_CENTER) * layouts.HYPER_SCALE
    for cam in all_cameras(info):
        np.testing.assert_allclose(intensity_centroid(cam.image), project(cam, point), atol=0.05)


def test_marker_in_downscaled_folder_checks_intrinsics_scaling(tmp_path):
    """images_2 holds half-size copies while poses_bounds keeps the full-size H, W, focal."""
    marker = make_marker_scene()
    gt = layouts.write_nvidia(marker, tmp_path / "s", folder="images_2", downscale=2, disp=False, masks=False)
    info = load_scene(tmp_path / "s", images="images_2")
    for cam in info.train_cameras:
        np.testing.assert_allclose(cam.K.numpy(), gt["K"], atol=1e-5)  # fx 40, cx 24: scaled by 1/2
        assert (cam.width, cam.height) == (32, 32)
        np.testing.assert_allclose(intensity_centroid(cam.image), project(cam, MARKER_POINT), atol=0.05)


def test_nvidia_times_eval_split_masks_and_disparity(tmp_path):
    scene = make_scene(num_frames=10)
    layouts.write_nvidia(scene, tmp_path / "s")
    info = load_scene(tmp_path / "s", eval=True)
    assert [c.frame_index for c in info.test_cameras] == [0, 8]
    assert [c.frame_index for c in info.train_cameras] == [1, 2, 3, 4, 5, 6, 7, 9]
    assert [c.uid for c in info.train_cameras] == list(range(8))
    np.testing.assert_allclose([c.time for c in info.train_cameras], np.array([1, 2, 3, 4, 5, 6, 7, 9]) / 9)
    assert info.num_frames == 10 and info.near_far == (scene.near, scene.far)
    cam = info.test_cameras[1]
    frame = scene.render(8)
    np.testing.assert_array_equal(cam.mask.numpy(), frame.dynamic.astype(np.float32))
    np.testing.assert_allclose(cam.disparity.numpy(), 1.0 / frame.depth, rtol=1e-6)
    np.testing.assert_allclose(cam.extras["near_far"].numpy(), [scene.near, scene.far])
    no_eval = load_scene(tmp_path / "s")
    assert len(no_eval.train_cameras) == 10 and no_eval.test_cameras == []
    held = load_scene(tmp_path / "s", eval=True, llffhold=4)
    assert [c.frame_index for c in held.test_cameras] == [0, 4, 8]


def test_resolution_rule_matches_3dgs():
    assert target_size(1352, 1014, 1) == (1352, 1014)
    assert target_size(1352, 1014, 4) == (338, 254)  # round(253.5) = 254 (Python rounding)
    assert target_size(1000, 500, -1) == (1000, 500)
    assert target_size(3200, 1801, -1) == (1600, 900)  # int() truncation as in 3DGS
    assert target_size(1000, 501, 400) == (400, 200)


def test_resolution_scales_images_masks_disparity_and_intrinsics(scene, tmp_path):
    layouts.write_nvidia(scene, tmp_path / "s")
    full = load_scene(tmp_path / "s").train_cameras[3]
    for resolution, size in ((2, (48, 48)), (64, (64, 64))):
        cam = load_scene(tmp_path / "s", resolution=resolution).train_cameras[3]
        assert (cam.width, cam.height) == size
        s = size[0] / 96
        np.testing.assert_allclose(cam.K.numpy(), np.diag([s, s, 1.0]) @ scene.K, atol=1e-5)
        assert cam.image.shape == (*size[::-1], 3) and cam.mask.shape == size[::-1] == cam.disparity.shape
        expected = cv2.resize(full.image.numpy(), size, interpolation=cv2.INTER_AREA)
        np.testing.assert_allclose(cam.image.numpy(), expected, atol=1e-6)
        assert set(np.unique(cam.mask.numpy())) <= {0.0, 1.0}  # nearest neighbour keeps it binary
        assert 0 < cam.mask.mean() < 1
        np.testing.assert_allclose(cam.disparity.mean(), full.disparity.mean(), rtol=0.05)


def test_resolution_minus_one_caps_width_at_1600(tmp_path, caplog):
    scene = make_scene(num_frames=2, width=1700, height=8, focal=900.0)
    scene.supersample = 1
    layouts.write_nvidia(scene, tmp_path / "wide", disp=False, masks=False)
    with caplog.at_level(logging.INFO, logger="baselines.data"):
        cam = load_scene(tmp_path / "wide").train_cameras[0]
    assert (cam.width, cam.height) == (1600, 7)  # int(8 / (1700 / 1600))
    assert cam.K[0, 0].item() == pytest.approx(900.0 * 1600 / 1700, rel=1e-6)
    assert cam.K[1, 1].item() == pytest.approx(900.0 * 7 / 8, rel=1e-6)
    assert sum("1600" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.parametrize("white", [False, True])
def test_dnerf_rgba_compositing_times_and_splits(scene, tmp_path, white):
    layouts.write_dnerf(scene, tmp_path / "d", num_test=2, time_scale=0.7)
    info = load_scene(tmp_path / "d", white_background=white, eval=True)
    assert len(info.train_cameras) == 6 and len(info.test_cameras) == 2
    assert [c.image_name for c in info.test_cameras] == ["test/r_006", "test/r_007"]
    np.testing.assert_allclose([c.time for c in info.train_cameras + info.test_cameras], scene.times, atol=1e-6)
    cam = info.train_cameras[2]
    raw = cv2.imread(str(tmp_path / "d" / "train" / "r_002.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 255
    rgb, alpha = raw[..., 2::-1], raw[..., 3:]
    expected = rgb * alpha + (1.0 if white else 0.0) * (1 - alpha)
    np.testing.assert_allclose(cam.image.numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(cam.extras["alpha"].numpy(), alpha[..., 0], atol=1e-6)
    assert np.allclose(cam.image.numpy()[:, :10], 1.0 if white else 0.0)  # alpha 0 on the left quarter
    merged = load_scene(tmp_path / "d")
    assert len(merged.train_cameras) == 8 and merged.test_cameras == []
    np.testing.assert_allclose(merged.scene_box, [[-1.3] * 3, [1.3] * 3])


def test_hypernerf_center_scale_resolutions_and_points(scene, tmp_path):
    gt = layouts.write_hypernerf(scene, tmp_path / "h", points=True)
    default = load_scene(tmp_path / "h", **NORMALISED["hypernerf"])  # resolution -1 -> rgb/2x, as 4DGS
    half_K = np.diag([0.5, 0.5, 1.0]) @ scene.K
    for cam in all_cameras(default):
        assert (cam.width, cam.height) == (48, 48)
        np.testing.assert_allclose(cam.K.numpy(), half_K, atol=1e-5)
        np.testing.assert_allclose(cam.viewmat.numpy(), gt["viewmats"][cam.frame_index], atol=1e-5)
    centre = default.train_cameras[1].camera_center.numpy()
    raw_centre = np.linalg.inv(scene.viewmats[default.train_cameras[1].frame_index])[:3, 3]
    np.testing.assert_allclose(centre, (raw_centre - layouts.HYPER_CENTER) * layouts.HYPER_SCALE, atol=1e-5)
    np.testing.assert_allclose(default.point_cloud.points,
                               (gt["raw_points"] - layouts.HYPER_CENTER) * layouts.HYPER_SCALE, atol=1e-5)
    assert default.near_far == pytest.approx((scene.near * layouts.HYPER_SCALE, scene.far * layouts.HYPER_SCALE))
    assert default.metadata["scene_scale"] == layouts.HYPER_SCALE
    derived = load_scene(tmp_path / "h", resolution=4, **NORMALISED["hypernerf"])  # no rgb/4x: derived from rgb/2x
    cam = derived.train_cameras[0]
    assert (cam.width, cam.height) == (24, 24)
    np.testing.assert_allclose(cam.K.numpy(), np.diag([0.25, 0.25, 1.0]) @ scene.K, atol=1e-5)
    by_width = load_scene(tmp_path / "h", resolution=60, **NORMALISED["hypernerf"]).train_cameras[0]
    assert by_width.width == 60


def test_hypernerf_raw_frame_option_matches_4dgs(scene, tmp_path):
    gt_points = layouts.write_hypernerf(scene, tmp_path / "h", points=True, scales=(1,))["raw_points"]
    raw = load_scene(tmp_path / "h", resolution=1)  # default: 4DGS's raw frame
    for cam in all_cameras(raw):
        np.testing.assert_allclose(cam.viewmat.numpy(), scene.viewmats[cam.frame_index], atol=1e-5)
    np.testing.assert_allclose(raw.point_cloud.points, gt_points, atol=1e-5)
    assert raw.near_far == pytest.approx((scene.near, scene.far))
    with pytest.raises(ValueError, match="apply_scene_transform"):
        load_scene(tmp_path / "h", dataset_type="nvidia", reader_options={"apply_scene_transform": False})


def test_hypernerf_interp_and_vrig_splits_and_times(tmp_path):
    scene = make_scene(num_frames=11, width=32, height=32, focal=27.0)
    layouts.write_hypernerf(scene, tmp_path / "interp", scales=(1,))
    interp = load_scene(tmp_path / "interp", resolution=1)
    assert [c.image_name for c in interp.train_cameras] == ["000", "004", "008"]
    assert [c.image_name for c in interp.test_cameras] == ["002", "006"]  # 4DGS drops the last (010)
    np.testing.assert_allclose([c.time for c in interp.test_cameras], [0.2, 0.6])
    assert interp.metadata["split"] == "interp" and interp.num_frames == 11
    layouts.write_hypernerf(scene, tmp_path / "vrig", vrig=True, scales=(1,))
    vrig = load_scene(tmp_path / "vrig", resolution=1)
    assert [c.frame_index for c in vrig.train_cameras] == [0, 2, 4, 6, 8, 10]
    assert [c.frame_index for c in vrig.test_cameras] == [1, 3, 5, 7, 9]
    assert {c.camera_id for c in vrig.test_cameras} == {1} and vrig.metadata["split"] == "vrig"


def test_hypernerf_camera_json_aspect_and_skew(tmp_path):
    from baselines.data.hypernerf import _read_camera

    path = tmp_path / "cam.json"
    R = np.eye(3)
    path.write_text(json.dumps({"orientation": R.tolist(), "position": [1.0, 2.0, 3.0], "focal_length": 100.0,
                                "principal_point": [50.0, 40.0], "image_size": [100, 80], "skew": 0.5,
                                "pixel_aspect_ratio": 1.1, "radial_distortion": [0.1, 0, 0],
                                "tangential_distortion": [0, 0]}))
    viewmat, K, size, distorted = _read_camera(path, np.array([1.0, 0.0, 0.0]), 2.0)
    np.testing.assert_allclose(K, [[100, 0.5, 50], [0, 110, 40], [0, 0, 1]])
    np.testing.assert_allclose(viewmat[:3, 3], -np.array([0.0, 4.0, 6.0]))
    assert size == (100, 80) and distorted


@pytest.mark.parametrize("text", [False, True])
def test_colmap_text_and_binary_models_order_by_name(scene, tmp_path, text):
    gt = layouts.write_colmap(scene, tmp_path / "c", text=text)
    info = load_scene(tmp_path / "c", eval=True)
    assert [c.image_name for c in info.test_cameras] == ["000"]
    cams = all_cameras(info)
    assert [c.image_name for c in cams] == [f"{i:03d}" for i in range(8)]
    np.testing.assert_allclose([c.time for c in cams], np.arange(8) / 7)
    distance = np.linalg.norm(info.point_cloud.points[:, None] - gt["points"][None], axis=2).min(axis=1)
    assert len(info.point_cloud) == len(gt["points"]) and distance.max() < 1e-5  # COLMAP stores points unordered
    np.testing.assert_allclose(info.point_cloud.colors[0], [10 / 255, 20 / 255, 30 / 255], atol=1e-6)


def test_colmap_distorted_model_warns_and_keeps_pinhole_part(scene, tmp_path, caplog):
    layouts.write_colmap(scene, tmp_path / "c", model="SIMPLE_RADIAL", points=False)
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        info = load_scene(tmp_path / "c")
    np.testing.assert_allclose(info.train_cameras[0].K.numpy(), scene.K, atol=1e-5)
    assert info.point_cloud is None
    assert any("SIMPLE_RADIAL" in r.getMessage() and "ignored" in r.getMessage() for r in caplog.records)


def test_scene_normalisation_and_video_cameras(scene, tmp_path):
    layouts.write_nvidia(scene, tmp_path / "s", disp=False, masks=False)
    info = load_scene(tmp_path / "s", eval=True)
    centres = np.stack([np.linalg.inv(scene.viewmats[c.frame_index])[:3, 3] for c in info.train_cameras])
    mean = centres.mean(0)
    np.testing.assert_allclose(info.nerf_normalization["translate"], -mean, atol=1e-5)
    assert info.nerf_normalization["radius"] == pytest.approx(1.1 * np.linalg.norm(centres - mean, axis=1).max(), rel=1e-5)
    video = info.video_cameras
    assert len(video) == info.num_frames == 8
    np.testing.assert_allclose([c.time for c in video], np.linspace(0, 1, 8))
    assert all(c.image is None and torch.equal(c.viewmat, info.train_cameras[0].viewmat) for c in video)


def test_camera_to_device_and_validation():
    cam = Camera(uid=0, image_name="a", width=4, height=3, K=np.eye(3), viewmat=np.eye(4), time=0.5,
                 image=torch.zeros(3, 4, 3), mask=torch.ones(3, 4), extras={"alpha": torch.ones(3, 4)})
    moved = cam.to("meta")
    assert moved.image.device.type == "meta" and moved.extras["alpha"].device.type == "meta"
    assert cam.image.device.type == "cpu"
    with pytest.raises(ValueError, match="image"):
        Camera(uid=0, image_name="a", width=4, height=3, K=np.eye(3), viewmat=np.eye(4), time=0.5,
               image=torch.zeros(4, 4, 3))
    with pytest.raises(ValueError, match="time"):
        Camera(uid=0, image_name="a", width=4, height=3, K=np.eye(3), viewmat=np.eye(4), time=1.5)
