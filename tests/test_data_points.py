"""Initial point clouds: dataset file, pycolmap triangulation from known cameras, random fallback."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from baselines.data import DatasetError, PointCloud, initial_point_cloud, load_scene, triangulate_static_points
from tests.data_fixtures import layouts
from tests.data_fixtures.scene import make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene(num_frames=8)


@pytest.fixture(scope="module")
def nvidia_scene(scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("nv") / "s"
    layouts.write_nvidia(scene, root, disp=False)
    return load_scene(root)


def test_dataset_point_file_is_used_first(scene, tmp_path):
    layouts.write_nvidia(scene, tmp_path / "s", disp=False, masks=False, points=True)
    info = load_scene(tmp_path / "s")
    cloud, source = initial_point_cloud(info)
    assert source == "dataset" and len(cloud) == 500
    assert np.allclose(cloud.colors, 200 / 255)
    assert scene.static_distance(cloud.points.astype(np.float64)).max() < 1e-5
    small, source = initial_point_cloud(info, max_points=50, seed=3)
    assert source == "dataset" and len(small) == 50
    assert np.isin(small.points, cloud.points).all(axis=1).all()


def test_colmap_points3d_is_the_dataset_cloud(scene, tmp_path):
    layouts.write_colmap(scene, tmp_path / "c")
    cloud, source = initial_point_cloud(load_scene(tmp_path / "c"))
    assert source == "dataset" and len(cloud) == 200


def test_triangulated_points_lie_on_static_surfaces_and_skip_masked_regions(scene, nvidia_scene):
    cloud, source = initial_point_cloud(nvidia_scene, min_points=20)
    assert source == "triangulated"
    points = cloud.points.astype(np.float64)
    assert len(points) >= 20
    # About one pixel at these depths is 0.06 units: the median point sits on a true surface.
    assert np.median(scene.static_distance(points)) < 0.1
    # Nothing on the moving panel (its features are masked out) ...
    assert (scene.dynamic_distance(points) < 0.05).sum() == 0
    # ... and every observation lies outside the motion masks.
    result = triangulate_static_points(nvidia_scene.train_cameras)
    cams = nvidia_scene.train_cameras
    for camera_index, xy in zip(result.obs_camera, result.obs_xy):
        mask = cams[camera_index].mask.numpy()
        assert mask[int(xy[1]), int(xy[0])] == 0
    # Reprojection of each point into its observations is consistent with the known cameras.
    errors = []
    for point_index, camera_index, xy in zip(result.obs_point, result.obs_camera, result.obs_xy):
        cam = cams[camera_index]
        p = cam.viewmat.double().numpy() @ np.append(result.points[point_index], 1.0)
        uv = (cam.K.double().numpy() @ p[:3])[:2] / p[2]
        errors.append(np.linalg.norm(uv - xy))
    assert np.median(errors) < 0.5


def test_without_masks_the_moving_panel_is_triangulated(scene, nvidia_scene):
    """Control for the test above: the moving panel IS matchable, so the masks do the work."""
    unmasked = [c.to("cpu") for c in nvidia_scene.train_cameras]
    for c in unmasked:
        c.mask = None
    result = triangulate_static_points(unmasked)
    assert (scene.dynamic_distance(result.points.astype(np.float64)) < 0.05).sum() >= 3


def test_unmatchable_images_fall_back_to_random_points_in_the_frusta(scene, tmp_path, caplog):
    layouts.write_nvidia(scene, tmp_path / "blank", disp=False, masks=False, blank=True)
    info = load_scene(tmp_path / "blank")
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        cloud, source = initial_point_cloud(info, random_points=500, seed=1)
    assert source == "random" and len(cloud) == 500
    assert any("falling back" in r.getMessage() for r in caplog.records)
    # Each point lies between near and far inside at least one training frustum.
    inside = np.zeros(len(cloud), bool)
    for cam in info.train_cameras:
        p = cloud.points.astype(np.float64) @ cam.viewmat[:3, :3].double().numpy().T + cam.viewmat[:3, 3].double().numpy()
        uv = (p @ cam.K.double().numpy().T)[:, :2] / p[:, 2:]
        inside |= ((p[:, 2] >= scene.near - 1e-4) & (p[:, 2] <= scene.far + 1e-4)
                   & (uv >= 0).all(1) & (uv[:, 0] <= cam.width) & (uv[:, 1] <= cam.height))
    assert inside.all()
    assert np.allclose(cloud.colors, 0.5, atol=1 / 255)  # colours come from the (grey) images
    again, _ = initial_point_cloud(info, random_points=500, seed=1)
    np.testing.assert_array_equal(again.points, cloud.points)  # seeded
    with pytest.raises(DatasetError, match="triangulated"):
        initial_point_cloud(info, method="triangulated")


def test_random_init_uses_the_dataset_box(scene, tmp_path):
    layouts.write_dnerf(scene, tmp_path / "d")
    info = load_scene(tmp_path / "d")
    cloud, source = initial_point_cloud(info, method="random", random_points=300)
    assert source == "random" and len(cloud) == 300
    assert (np.abs(cloud.points) <= 1.3).all() and np.abs(cloud.points).max() > 1.0


def test_method_validation(nvidia_scene):
    with pytest.raises(DatasetError, match="no point file"):
        initial_point_cloud(nvidia_scene, method="dataset")
    with pytest.raises(DatasetError, match="unknown initial point method"):
        initial_point_cloud(nvidia_scene, method="sfm")


def test_point_cloud_validation():
    cloud = PointCloud(np.zeros((2, 3)), np.ones((2, 3)))
    assert cloud.points.dtype == np.float32 and cloud.normals is None
    with pytest.raises(DatasetError, match="points"):
        PointCloud(np.zeros((2, 2)), np.ones((2, 3)))
    with pytest.raises(DatasetError, match="non-finite"):
        PointCloud(np.array([[0.0, np.nan, 0.0]]), np.ones((1, 3)))
    with pytest.raises(DatasetError, match="colours"):
        PointCloud(np.zeros((1, 3)), np.full((1, 3), 2.0))
    with pytest.raises(DatasetError, match="colours"):
        PointCloud(np.zeros((2, 3)), np.ones((1, 3)))


def test_seeded_triangulation_is_bit_identical_across_runs(nvidia_scene):
    first = triangulate_static_points(nvidia_scene.train_cameras, seed=5)
    second = triangulate_static_points(nvidia_scene.train_cameras, seed=5)
    assert len(first) > 0
    for name in ("points", "colors", "errors", "obs_point", "obs_camera", "obs_xy"):
        assert np.array_equal(getattr(first, name), getattr(second, name)), name


def _cube_behind_the_cameras(info, count=3000, seed=0):
    """A random cube (the placeholder seen in real copies) placed where no training camera looks."""
    centres = np.stack([-c.viewmat[:3, :3].double().numpy().T @ c.viewmat[:3, 3].double().numpy()
                        for c in info.train_cameras])
    forward = np.stack([c.viewmat[2, :3].double().numpy() for c in info.train_cameras]).mean(axis=0)
    centre = centres.mean(axis=0) - 50.0 * forward / np.linalg.norm(forward)
    points = np.random.default_rng(seed).uniform(centre - 5.0, centre + 5.0, size=(count, 3))
    return PointCloud(points, np.full((count, 3), 0.5))


def test_placeholder_cloud_no_camera_sees_falls_back(scene, nvidia_scene, caplog):
    import dataclasses

    from baselines.data.cloud_check import check_cloud_against_cameras

    placeholder = dataclasses.replace(nvidia_scene, point_cloud=_cube_behind_the_cameras(nvidia_scene))
    coverage = check_cloud_against_cameras(placeholder.point_cloud.points, placeholder.train_cameras)
    assert not coverage.passed and coverage.views_seeing == 0.0 and coverage.in_front.max() == 0.0
    with caplog.at_level(logging.WARNING, logger="baselines.data"):
        cloud, source = initial_point_cloud(placeholder, min_points=20)
    assert source == "triangulated"
    assert any("placeholder" in r.getMessage() and "0 of" in r.getMessage() for r in caplog.records)
    forced, source = initial_point_cloud(placeholder, check_dataset_points=False)
    assert source == "dataset" and len(forced) == 3000
    # a real reconstruction (points on the scene's static surfaces) passes the check
    real = check_cloud_against_cameras(layouts.static_surface_points(scene), nvidia_scene.train_cameras)
    assert real.passed, real.summary()
