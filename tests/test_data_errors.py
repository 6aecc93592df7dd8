"""Every bad input gives one `DatasetError` whose message names the culprit file."""
from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from baselines.data import DatasetError, load_scene
from tests.data_fixtures import layouts
from tests.data_fixtures.scene import make_scene


@pytest.fixture(scope="module")
def tiny():
    return make_scene(num_frames=4, width=32, height=32, focal=27.0)


@pytest.fixture(scope="module")
def templates(tiny, tmp_path_factory):
    """One clean copy of each layout; tests mutate a fresh copy of it."""
    root = tmp_path_factory.mktemp("templates")
    layouts.write_nvidia(tiny, root / "nvidia")
    layouts.write_dnerf(tiny, root / "dnerf", num_test=1)
    layouts.write_hypernerf(tiny, root / "hypernerf", scales=(1,))
    layouts.write_colmap(tiny, root / "colmap")
    return root


@pytest.fixture
def copy_of(templates, tmp_path):
    copies = iter(range(1000))

    def make(layout: str):
        target = tmp_path / f"{layout}_{next(copies)}"
        shutil.copytree(templates / layout, target)
        return target
    return make


def expect_error(path, *names, **kwargs):
    with pytest.raises(DatasetError) as info:
        load_scene(path, **kwargs)
    for name in names:
        assert str(name) in str(info.value), f"{name!r} not in: {info.value}"
    return str(info.value)


def corrupt(path):
    path.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")


def edit_json(path, change):
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


# --- nvidia -------------------------------------------------------------------------------

def test_nvidia_missing_poses_file(copy_of):
    root = copy_of("nvidia")
    (root / "poses_bounds.npy").unlink()
    expect_error(root, "poses_bounds.npy", dataset_type="nvidia")


def test_nvidia_image_count_differs_from_pose_count(copy_of):
    root = copy_of("nvidia")
    (root / "images" / "003.png").unlink()
    expect_error(root, "images", "poses_bounds.npy", "3 images", "4 poses")


def test_nvidia_missing_image_folder_lists_alternatives(copy_of):
    root = copy_of("nvidia")
    (root / "images").rename(root / "images_2")
    expect_error(root, "images", "images_2")


def test_nvidia_corrupt_image(copy_of):
    root = copy_of("nvidia")
    corrupt(root / "images" / "002.png")
    expect_error(root, "002.png")


def test_nvidia_truncated_jpeg_frame(copy_of):
    """OpenCV decodes a JPEG cut short without an error, its missing rows flat grey."""
    root = copy_of("nvidia")
    png = root / "images" / "002.png"
    jpeg = png.with_suffix(".jpg")
    cv2.imwrite(str(jpeg), cv2.imread(str(png)), [cv2.IMWRITE_JPEG_QUALITY, 100])
    png.unlink()
    assert len(load_scene(root).train_cameras) == 4  # the whole JPEG loads
    data = jpeg.read_bytes()
    jpeg.write_bytes(data[:len(data) * 2 // 3])
    expect_error(root, "002.jpg", "truncated")


def test_nvidia_inconsistent_image_sizes(copy_of):
    root = copy_of("nvidia")
    other = make_scene(num_frames=1, width=16, height=16, focal=13.5).render(0).rgb
    layouts.write_rgb(root / "images" / "001.png", other)
    expect_error(root, "001.png")


@pytest.mark.parametrize("row, col, value, message", [
    (2, 4, np.nan, "non-finite"),          # NaN in a rotation entry
    (1, 16, np.inf, "non-finite"),         # inf far bound
    (0, 14, 0.0, "focal"),                 # zero focal
    (3, 14, -5.0, "focal"),                # negative focal
    (1, 15, 12.0, "bounds"),               # near > far
    (2, 0, 3.0, "rotation"),               # not a rotation
])
def test_nvidia_bad_pose_values(copy_of, row, col, value, message):
    root = copy_of("nvidia")
    poses = np.load(root / "poses_bounds.npy")
    poses[row, col] = value
    np.save(root / "poses_bounds.npy", poses)
    expect_error(root, "poses_bounds.npy", message)


def test_nvidia_malformed_and_misshapen_npy(copy_of):
    root = copy_of("nvidia")
    (root / "poses_bounds.npy").write_bytes(b"garbage")
    expect_error(root, "poses_bounds.npy", "malformed")
    np.save(root / "poses_bounds.npy", np.zeros((4, 16)))
    expect_error(root, "poses_bounds.npy", "[N, 17]")


def test_nvidia_disparity_problems(copy_of):
    root = copy_of("nvidia")
    np.save(root / "disp" / "001.npy", np.full((32, 32), np.nan, np.float32))
    expect_error(root, "001.npy", "non-finite")
    (root / "disp" / "001.npy").unlink()
    expect_error(root, "disp", "3 files")


def test_nvidia_empty_disparity_and_complex_poses(copy_of):
    """A 0x0 disparity map reached cv2.resize (a traceback); complex poses lost their imaginary part."""
    root = copy_of("nvidia")
    np.save(root / "disp" / "001.npy", np.zeros((0, 0), np.float32))
    expect_error(root, "001.npy", "(0, 0)")
    root = copy_of("nvidia")
    np.save(root / "poses_bounds.npy", np.load(root / "poses_bounds.npy").astype(np.complex64))
    expect_error(root, "poses_bounds.npy", "numeric", "complex64")


def test_nvidia_corrupt_mask(copy_of):
    root = copy_of("nvidia")
    corrupt(root / "motion_masks" / "000.png")
    expect_error(root, "000.png", "mask")


def test_nvidia_corrupt_point_file(copy_of):
    root = copy_of("nvidia")
    (root / "points3D.ply").write_text("ply\nformat nonsense\n")
    expect_error(root, "points3D.ply")


# --- dnerf --------------------------------------------------------------------------------

def test_dnerf_malformed_json(copy_of):
    root = copy_of("dnerf")
    (root / "transforms_train.json").write_text("{not json")
    expect_error(root, "transforms_train.json", "malformed")


@pytest.mark.parametrize("change, message", [
    (lambda d: d["frames"][1].pop("transform_matrix"), "transform_matrix"),
    (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan")), "non-finite"),
    (lambda d: d["frames"][2].__setitem__("time", float("inf")), "time"),
    (lambda d: d.__setitem__("camera_angle_x", -0.5), "camera_angle_x"),
    (lambda d: d.pop("camera_angle_x"), "fl_x"),
    (lambda d: d["frames"][0].__setitem__("file_path", "./train/missing"), "missing"),
    (lambda d: d.__setitem__("frames", []), "frames"),
])
def test_dnerf_bad_transforms(copy_of, change, message):
    root = copy_of("dnerf")
    edit_json(root / "transforms_train.json", change)
    expect_error(root, "transforms_train.json", message)


def test_dnerf_eval_needs_test_split(copy_of):
    root = copy_of("dnerf")
    (root / "transforms_test.json").unlink()
    expect_error(root, "transforms_test.json", eval=True)
    assert len(load_scene(root).train_cameras) == 3  # without eval the test file is optional


def test_dnerf_corrupt_image(copy_of):
    root = copy_of("dnerf")
    corrupt(root / "train" / "r_001.png")
    expect_error(root, "r_001.png")


# --- hypernerf ----------------------------------------------------------------------------

@pytest.mark.parametrize("change, message", [
    (lambda d: d.__setitem__("position", [0.0, float("nan"), 1.0]), "position"),
    (lambda d: d.__setitem__("focal_length", 0.0), "focal_length"),
    (lambda d: d.__setitem__("orientation", [[1, 0], [0, 1]]), "orientation"),
    (lambda d: d.pop("principal_point"), "principal_point"),
])
def test_hypernerf_bad_camera_json(copy_of, change, message):
    root = copy_of("hypernerf")
    edit_json(root / "camera" / "002.json", change)
    expect_error(root, "002.json", message)


def test_hypernerf_missing_files(copy_of):
    root = copy_of("hypernerf")
    (root / "camera" / "001.json").unlink()
    expect_error(root, "001.json")
    root = copy_of("hypernerf")
    shutil.rmtree(root / "rgb")
    expect_error(root, "rgb")


def test_hypernerf_missing_image(copy_of):
    root = copy_of("hypernerf")
    (root / "rgb" / "1x" / "003.png").unlink()
    expect_error(root, "003.png", resolution=1)


def test_hypernerf_bad_metadata_and_scene(copy_of):
    root = copy_of("hypernerf")
    edit_json(root / "metadata.json", lambda d: d.pop("001"))
    expect_error(root, "metadata.json", "001")
    root = copy_of("hypernerf")
    edit_json(root / "scene.json", lambda d: d.__setitem__("scale", -1.0))
    expect_error(root, "scene.json", "scale")
    root = copy_of("hypernerf")
    edit_json(root / "dataset.json", lambda d: d.__setitem__("val_ids", ["999"]))
    expect_error(root, "dataset.json", "999")


def test_hypernerf_scene_without_near_far_loads_without_bounds_and_a_nan_near_is_refused(copy_of):
    root = copy_of("hypernerf")
    edit_json(root / "scene.json", lambda d: (d.pop("near", None), d.pop("far", None)))
    assert load_scene(root, resolution=1).near_far is None  # optional keys: absent means no bounds
    root = copy_of("hypernerf")
    edit_json(root / "scene.json", lambda d: d.__setitem__("near", float("nan")))
    expect_error(root, "scene.json", "near")


def test_hypernerf_resolution_without_a_finer_folder(copy_of):
    root = copy_of("hypernerf")
    (root / "rgb" / "1x").rename(root / "rgb" / "2x")
    expect_error(root, "rgb/1x", resolution=1)


# --- colmap -------------------------------------------------------------------------------

def test_colmap_missing_image_and_folder(copy_of):
    root = copy_of("colmap")
    (root / "images" / "002.png").unlink()
    expect_error(root, "002.png")
    shutil.rmtree(root / "images")
    expect_error(root, "images")


def test_colmap_two_masks_for_one_image(copy_of):
    """000.png and 000.jpg: the folder listing's order would pick one; a notes file is no mask."""
    root = copy_of("colmap")
    (root / "motion_masks").mkdir()
    for k in range(4):
        cv2.imwrite(str(root / "motion_masks" / f"{k:03d}.png"), np.zeros((32, 32), np.uint8))
    (root / "motion_masks" / "001.txt").write_text("made with tool X")
    assert load_scene(root).train_cameras[1].mask is not None
    cv2.imwrite(str(root / "motion_masks" / "001.jpg"), np.full((32, 32), 255, np.uint8))
    expect_error(root, "motion_masks", "2 masks for image '001.png'", "001.jpg", "001.png")


def test_colmap_corrupt_model(copy_of):
    root = copy_of("colmap")
    (root / "sparse" / "0" / "images.bin").write_bytes(b"\x01\x02")
    expect_error(root, "sparse/0")


def test_colmap_unsupported_camera_model(tiny, tmp_path):
    layouts.write_colmap(tiny, tmp_path / "c", model="OPENCV_FISHEYE", points=False)
    expect_error(tmp_path / "c", "OPENCV_FISHEYE", "sparse/0")


# --- dispatch and arguments ---------------------------------------------------------------

def test_unknown_layout_lists_what_was_looked_for(tmp_path):
    (tmp_path / "notes.txt").write_text("nothing here")
    message = expect_error(tmp_path, str(tmp_path))
    for looked_for in ("poses_bounds.npy", "transforms_train.json", "dataset.json", "sparse/0"):
        assert looked_for in message


def test_unknown_type_missing_folder_and_bad_resolution(copy_of, tmp_path):
    expect_error(tmp_path / "nope", "nope")
    root = copy_of("nvidia")
    expect_error(root, "dataset_type", "kinect", dataset_type="kinect")
    expect_error(root, "resolution", resolution=0)
    expect_error(root, "llffhold", eval=True, llffhold=0)
