"""Output layout of the synthetic simulator: LLFF poses, depth/disparity, masks, splits, vrig,
determinism and crash-safe publishing."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from baselines.synthetic import SceneObject, SceneSpec, StaticCamera, Texture, get_scene, simulate
from baselines.synthetic.simulate import sample_frame

TINY = dict(frames=10, width=40, height=32)


@pytest.fixture(scope="module")
def balloon(tmp_path_factory):
    spec = get_scene("balloon", **TINY)
    return spec, simulate(spec, tmp_path_factory.mktemp("balloon") / "balloon", progress=False)


@pytest.fixture(scope="module")
def static(tmp_path_factory):
    spec = get_scene("static", frames=9, width=32, height=24)
    return spec, simulate(spec, tmp_path_factory.mktemp("static") / "static", progress=False)


def _cameras(root: Path, sub: str = "") -> list[dict]:
    return json.loads((root / "gt" / sub / "cameras.json").read_text())["frames"]


def _mask(root: Path, i: int) -> np.ndarray:
    image = cv2.imread(str(root / "motion_masks" / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint8 and image.ndim == 2 and set(np.unique(image)) <= {0, 255}
    return image > 0


def test_layout_and_file_formats(balloon):
    spec, root = balloon
    n = spec.frames
    names = [f"{i:03d}" for i in range(n)]
    assert sorted(p.stem for p in (root / "images").glob("*.png")) == names
    assert sorted(p.stem for p in (root / "gt" / "flow_fwd").glob("*.npy")) == names[:-1]
    assert sorted(p.stem for p in (root / "gt" / "occ_fwd").glob("*.png")) == names[:-1]
    assert sorted(p.stem for p in (root / "gt" / "flow_bwd").glob("*.npy")) == names[1:]
    assert sorted(p.stem for p in (root / "gt" / "occ_bwd").glob("*.png")) == names[1:]
    image = cv2.imread(str(root / "images" / "000.png"), cv2.IMREAD_UNCHANGED)
    assert image.shape == (spec.height, spec.width, 3) and image.dtype == np.uint8
    for folder, shape in (("disp", (32, 40)), ("gt/depth", (32, 40)), ("gt/flow_fwd", (32, 40, 2))):
        array = np.load(root / folder / "000.npy")
        assert array.dtype == np.float32 and array.shape == shape and np.isfinite(array).all()
    info = json.loads((root / "scene.json").read_text())
    assert info["effects"] == list(spec.effect_names)
    assert set(info["effects"]) >= {"shake", "vrig", "rigid"}
    assert info["seed"] == spec.seed and info["simulator_version"]
    assert SceneSpec.from_dict(info["spec"]) == spec  # the spec round-trips through scene.json
    cams = _cameras(root)
    assert [c["time"] for c in cams] == pytest.approx([i / (n - 1) for i in range(n)])
    assert all(c["width"] == 40 and c["height"] == 32 and c["camera_id"] == 0 for c in cams)


def test_poses_bounds_match_cameras_and_depth(balloon):
    spec, root = balloon
    poses_bounds = np.load(root / "poses_bounds.npy")
    assert poses_bounds.shape == (spec.frames, 17)
    cams = _cameras(root)
    for i, (row, cam) in enumerate(zip(poses_bounds, cams)):
        llff = row[:15].reshape(3, 5)
        h, w, focal = llff[:, 4]
        K = np.array(cam["K"])
        assert (h, w) == (spec.height, spec.width) and focal == pytest.approx(K[0, 0])
        assert K[0, 0] == pytest.approx(K[1, 1])
        np.testing.assert_allclose(K[:2, 2], [spec.width / 2, spec.height / 2])
        # LLFF columns are [down, right, back] = [y_cv, x_cv, -z_cv].
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = llff[:, 1], llff[:, 0], -llff[:, 2], llff[:, 3]
        np.testing.assert_allclose(np.linalg.inv(c2w), np.array(cam["viewmat"]), atol=1e-10)
        near, far = row[15:]
        depth = np.load(root / "gt" / "depth" / f"{i:03d}.npy")
        assert 0 < near <= depth.min() and depth.max() <= far
        np.testing.assert_allclose(np.load(root / "disp" / f"{i:03d}.npy"), 1.0 / depth, rtol=1e-6)


def test_depth_is_camera_z_not_ray_length(tmp_path):
    """Camera looking straight down -z at a room's back wall 8 units away: every pixel seeing the
    wall has depth exactly 8 (z-depth), including off-centre ones whose rays are longer."""
    room = SceneObject("room", "room", size=(3.5, 2.0, 4.5), position=(0.0, 2.0, -0.5),
                       texture=Texture("noise", period=0.5))
    spec = SceneSpec(name="wall", objects=(room,), camera=StaticCamera((0.0, 1.4, 3.0),
                                                                        (0.0, 1.4, -1.0)),
                     frames=2, width=16, height=12, supersample=1)
    root = simulate(spec, tmp_path / "wall", progress=False)
    depth = np.load(root / "gt" / "depth" / "000.npy")
    np.testing.assert_allclose(depth[3:8, 4:12], 8.0, rtol=1e-6)  # rows 8+ see the floor
    assert depth[6, 0] < 7.9  # the leftmost column sees the side wall, nearer


def test_static_scene_has_empty_masks(static):
    spec, root = static
    assert json.loads((root / "scene.json").read_text())["dynamic_objects"] == []
    assert not any(_mask(root, i).any() for i in range(spec.frames))


def test_masks_cover_exactly_the_dynamic_objects(balloon):
    """The mask is set exactly where removing the dynamic objects changes the visible depth."""
    spec, root = balloon
    dynamic = set(json.loads((root / "scene.json").read_text())["dynamic_objects"])
    assert dynamic == {"balloon", "string"}
    without = dataclasses.replace(spec, objects=tuple(o for o in spec.objects
                                                      if o.name not in dynamic))
    jj, ii = np.meshgrid(np.arange(spec.width) + 0.5, np.arange(spec.height) + 0.5)
    pixels = np.stack([jj, ii], axis=-1).reshape(-1, 2)
    for i in (0, 5, 9):
        mask = _mask(root, i)
        assert 0.01 < mask.mean() < 0.3
        depth = np.load(root / "gt" / "depth" / f"{i:03d}.npy")
        _, background = sample_frame(without, i, pixels)
        changed = np.abs(background.reshape(depth.shape) - depth) > 1e-5 * depth
        np.testing.assert_array_equal(mask, changed)


def test_split_holds_out_every_eighth_frame(balloon):
    spec, root = balloon
    split = json.loads((root / "gt" / "split.json").read_text())
    assert split["test"] == [0, 8]
    assert split["train"] == [1, 2, 3, 4, 5, 6, 7, 9]


def test_vrig_second_camera_at_fixed_offset(balloon):
    spec, root = balloon
    offset = np.array(spec.effect("vrig").offset)
    main, second = _cameras(root), _cameras(root, "vrig")
    assert len(second) == spec.frames
    assert len(list((root / "gt" / "vrig" / "images").glob("*.png"))) == spec.frames
    assert len(list((root / "gt" / "vrig" / "depth").glob("*.npy"))) == spec.frames
    for a, b in zip(main, second):
        va, vb = np.array(a["viewmat"]), np.array(b["viewmat"])
        assert a["time"] == b["time"] and b["camera_id"] != a["camera_id"]
        # Same orientation; centre displaced by the offset expressed in the main camera frame.
        np.testing.assert_allclose(va[:3, :3], vb[:3, :3], atol=1e-12)
        centre_a, centre_b = -va[:3, :3].T @ va[:3, 3], -vb[:3, :3].T @ vb[:3, 3]
        np.testing.assert_allclose(centre_b - centre_a, va[:3, :3].T @ offset, atol=1e-12)
    main_image = cv2.imread(str(root / "images" / "004.png"))
    vrig_image = cv2.imread(str(root / "gt" / "vrig" / "images" / "004.png"))
    assert np.abs(main_image.astype(int) - vrig_image).mean() > 1.0


def test_rig_cycles_through_fixed_cameras(tmp_path):
    spec = get_scene("hard_baseline", frames=9, width=24, height=16)
    root = simulate(spec, tmp_path / "rig", progress=False)
    cams = _cameras(root)
    assert [c["camera_id"] for c in cams] == [i % 4 for i in range(9)]
    for a in range(4):
        np.testing.assert_allclose(cams[a]["viewmat"], cams[a + 4]["viewmat"], atol=0)
    assert not np.allclose(cams[0]["viewmat"], cams[1]["viewmat"])


def _all_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_different_seed_different_images(tmp_path):
    spec = get_scene("playground", frames=3, width=24, height=20)
    first = _all_files(simulate(spec, tmp_path / "a", progress=False))
    second = _all_files(simulate(spec, tmp_path / "b", progress=False))
    assert first.keys() == second.keys() and len(first) > 10
    assert all(first[k] == second[k] for k in first)
    other = _all_files(simulate(spec.with_overrides(seed=7), tmp_path / "c", progress=False))
    images = [k for k in first if k.startswith("images/")]
    assert all(first[k] != other[k] for k in images)


def test_existing_output_replaced_foreign_directory_refused(tmp_path):
    out = tmp_path / "scene"
    simulate(get_scene("static", frames=4, width=16, height=12), out, progress=False)
    simulate(get_scene("static", frames=3, width=16, height=12), out, progress=False)
    assert len(list((out / "images").glob("*.png"))) == 3
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="refusing to overwrite"):
        simulate(get_scene("static", frames=3, width=16, height=12), foreign, progress=False)
    assert (foreign / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "scene"]  # no leftovers


def test_failed_run_leaves_nothing_behind(tmp_path):
    """A scene whose rays escape (no enclosing room) fails with a clear error, and neither the
    destination nor a staging directory remains."""
    spec = get_scene("balloon", frames=2, width=16, height=12)
    open_scene = dataclasses.replace(spec, objects=tuple(o for o in spec.objects
                                                         if o.name != "room"))
    with pytest.raises(ValueError, match="see no surface"):
        simulate(open_scene, tmp_path / "open", progress=False)
    assert list(tmp_path.iterdir()) == []
