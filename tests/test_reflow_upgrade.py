"""Upgrading 4DGS checkpoints to ReFlow: motion labels, baked static Gaussians, renders, errors, e2e."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from baselines.data.cameras import Camera
from baselines.fourdgs.app import build_trainer, finish_run, render_from_argv
from baselines.fourdgs.checkpoint import load_point_cloud_dir, ply_attribute_names
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.renderer import render
from benchmarks.deformation import PlainDeformNetwork
from reflow_plugin.separation import SeparatedDeformation
from reflow_plugin.upgrade import upgrade_4dgs_model, written_by_reflow
from tests._model_helpers import hidden_args
from tests.test_reflow_plugin import _argv

TIMES = [i / 7 for i in range(8)]
THRESHOLD = 0.01  # x extent 1.0


def _write_4dgs_folder(folder: Path, hidden, static_wobble: float, seed: int = 0) -> np.ndarray:
    """A point_cloud/iteration_N folder as 4DGaussians writes it (PLY + deformation.pth only).

    Gaussians at x < -0.35 (static) and x > 0.35 (dynamic) inside the HexPlane box [-1, 1]^3. The
    x-t planes are constant in t for x < 0 (up to ``static_wobble``) and random for x > 0, so only
    the right half moves. Returns the centres [N, 3].
    """
    rng = np.random.default_rng(seed)
    count = 60
    xyz = rng.uniform(-0.9, 0.9, (count, 3)).astype(np.float32)
    xyz[:, 0] = np.where(np.arange(count) % 2 == 0, rng.uniform(-0.9, -0.35, count), rng.uniform(0.35, 0.9, count))
    xyz[:, 2] *= 0.3
    coefficients = 4  # sh_degree 1
    features = rng.uniform(-0.5, 0.5, (count, 3, coefficients)).astype(np.float32)
    opacity = np.full((count, 1), 2.0, np.float32)
    scale = np.full((count, 3), np.log(0.06), np.float32)
    rotation = np.tile(np.array([1, 0, 0, 0], np.float32), (count, 1))
    attributes = np.concatenate((xyz, np.zeros_like(xyz), features[:, :, 0], features[:, :, 1:].reshape(count, -1),
                                 opacity, scale, rotation), axis=1)
    elements = np.empty(count, dtype=[(n, "f4") for n in ply_attribute_names(coefficients - 1)])
    elements[:] = list(map(tuple, attributes))
    folder.mkdir(parents=True)
    PlyData([PlyElement.describe(elements, "vertex")]).write(str(folder / "point_cloud.ply"))

    torch.manual_seed(seed)
    state = PlainDeformNetwork(hidden).state_dict()
    state["deformation_net.grid.aabb"] = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]])
    generator = torch.Generator().manual_seed(seed)
    for key in [k for k in state if k.startswith("deformation_net.grid.grids.") and k.endswith(".2")]:
        plane = state[key]  # the x-t plane: [1, C, res_t, res_x]
        res_x = plane.shape[-1]
        moving = 1.0 + 2.0 * torch.rand(plane.shape, generator=generator)
        wobble = 1.0 + static_wobble * torch.rand(plane.shape, generator=generator)
        # 4DGS stores aabb as [max, min]: plane column 0 is x = +1, so x > 0 is the left half
        plane[..., : res_x // 2] = moving[..., : res_x // 2]
        plane[..., res_x // 2:] = wobble[..., res_x // 2:]
    state["deformation_net.pos_deform.3.weight"] *= 50.0  # motions of a few hundredths of the box
    torch.save(state, folder / "deformation.pth")
    return xyz


def _camera(width: int = 48) -> Camera:
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[40.0, 0, width / 2], [0, 40.0, width / 2], [0, 0, 1]])
    return Camera(uid=0, image_name="c", width=width, height=width, K=K, viewmat=viewmat, time=0.0)


def _load(folder: Path, hidden, separated: bool) -> GaussianModel:
    deformation = SeparatedDeformation(hidden) if separated else None
    model = GaussianModel(1, hidden, deformation=deformation)
    load_point_cloud_dir(folder, model)
    model.active_sh_degree = 1
    return model


def _images(model: GaussianModel, times) -> list[torch.Tensor]:
    background = torch.zeros(3)
    out = []
    with torch.no_grad():
        for t in times:
            camera = _camera()
            camera.time = float(t)
            out.append(render(model, camera, "fine", background).image)
    return out


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fourdgs") / "point_cloud" / "iteration_14000"
    _write_4dgs_folder(path, hidden_args(), static_wobble=0.02)
    return path


def test_labels_follow_the_deformation_magnitude_and_static_gaussians_stay_within_the_threshold(folder):
    hidden = hidden_args()
    original = _load(folder, hidden, separated=False)
    upgraded = _load(folder, hidden, separated=True)
    report = upgrade_4dgs_model(upgraded, TIMES, THRESHOLD, extent=1.0, bake=True)

    dynamic = upgraded.deformation_table
    expected = original.get_xyz[:, 0] > 0
    assert torch.equal(dynamic, expected), (dynamic, expected)
    assert report["dynamic"] == int(expected.sum()) and report["static"] == int((~expected).sum())
    assert 0 < report["max_static_motion"] <= THRESHOLD  # the wobble is there, below the threshold
    with torch.no_grad():
        for t in TIMES + [0.5 / 7]:  # training times and one between them
            before, after = original.deform(t, "fine").means, upgraded.deform(t, "fine").means
            torch.testing.assert_close(after[dynamic], before[dynamic], rtol=0, atol=1e-6)
            moved = (after[~dynamic] - before[~dynamic]).norm(dim=-1)
            assert float(moved.max()) <= THRESHOLD * 1.05 and float(moved.max()) > 0
            # static Gaussians do not move over time any more
            torch.testing.assert_close(after[~dynamic], upgraded.deform(0.0, "fine").means[~dynamic])

    # Renders: a few hundredths of a pixel of displacement at most -> nearly the same images.
    for a, b in zip(_images(original, TIMES[::3]), _images(upgraded, TIMES[::3])):
        mse = float(((a - b) ** 2).mean())
        assert mse < 10 ** (-40 / 10), f"PSNR {-10 * np.log10(mse):.1f} dB between 4DGS and upgraded renders"


def test_without_separation_the_renders_are_identical(folder):
    hidden = hidden_args()
    original = _load(folder, hidden, separated=False)
    upgraded = _load(folder, hidden, separated=False)
    report = upgrade_4dgs_model(upgraded, TIMES, THRESHOLD, extent=1.0, bake=False)
    assert report["dynamic"] > 0 and not report["static_baked"]
    assert torch.equal(upgraded.get_xyz, original.get_xyz)
    for a, b in zip(_images(original, TIMES[::2]), _images(upgraded, TIMES[::2])):
        assert torch.equal(a, b)


def test_a_missing_or_mismatched_entry_is_named(folder, tmp_path):
    hidden = hidden_args()
    broken = tmp_path / "point_cloud" / "iteration_1"
    broken.mkdir(parents=True)
    (broken / "point_cloud.ply").write_bytes((folder / "point_cloud.ply").read_bytes())
    state = torch.load(folder / "deformation.pth")
    del state["deformation_net.pos_deform.3.weight"]
    torch.save(state, broken / "deformation.pth")
    with pytest.raises(Exception, match="pos_deform.3.weight"):
        _load(broken, hidden, separated=True)
    state = torch.load(folder / "deformation.pth")
    state["deformation_net.grid.grids.0.2"] = torch.ones(1, 4, 4, 3)
    torch.save(state, broken / "deformation.pth")
    with pytest.raises(Exception, match="grids.0.2"):
        _load(broken, hidden, separated=True)


@pytest.mark.parametrize("static_decoder", ["none", "field"])
def test_upgrade_through_train_py_and_render(tiny_scene, tmp_path, static_decoder):
    base = tmp_path / "fourdgs"
    argv = [a for a in _argv(tiny_scene, base, 10, 30) if a not in ("--plugin", "reflow")]
    argv = [a for i, a in enumerate(argv) if not (a == "--flow_vis_every" or argv[i - 1] == "--flow_vis_every")]
    trainer = build_trainer(argv)
    finish_run(trainer, trainer.train())
    checkpoint = base / "point_cloud" / "iteration_30"
    assert checkpoint.is_dir() and not written_by_reflow(checkpoint)
    (base / "config.json").unlink()  # as a 4DGaussians output: cfg_args only

    out = tmp_path / "upgraded"
    trainer = build_trainer(_argv(tiny_scene, out, 10, 10, "--start_checkpoint", str(checkpoint),
                                  "--upgrade_motion_threshold", "0.0", "--static_decoder", static_decoder))
    finish_run(trainer, trainer.train())
    results = json.loads((out / "results.json").read_text())
    upgrade = results["reflow"]["upgrade"]
    assert upgrade["dynamic"] + upgrade["static"] > 0
    assert upgrade["static_baked"] == (static_decoder != "field")  # the field carries 4DGS's motion
    assert written_by_reflow(out / "point_cloud" / "iteration_10")
    written = render_from_argv(["-m", str(out), "--skip_video"])
    assert (written["test"] / "renders" / "00000.png").is_file()


def _load_with(folder: Path, hidden, static_decoder: str) -> GaussianModel:
    model = GaussianModel(1, hidden, deformation=SeparatedDeformation(hidden, static_decoder))
    load_point_cloud_dir(folder, model)
    model.active_sh_degree = 1
    return model


def test_with_the_static_field_the_4dgs_motion_is_kept_and_nothing_is_baked(folder):
    hidden = hidden_args()
    original = _load(folder, hidden, separated=False)
    upgraded = _load_with(folder, hidden, "field")
    field_state = upgraded.deformation.static_field.state_dict()
    for key, value in torch.load(folder / "deformation.pth").items():  # the field is the 4DGS network
        assert torch.equal(field_state[key], value), key
    report = upgrade_4dgs_model(upgraded, TIMES, THRESHOLD, extent=1.0, bake=False)
    dynamic = upgraded.deformation_table
    assert torch.equal(dynamic, original.get_xyz[:, 0] > 0) and not report["static_baked"]
    with torch.no_grad():
        for t in TIMES + [0.5 / 7]:
            before, after = original.deform(t, "fine"), upgraded.deform(t, "fine")
            torch.testing.assert_close(after.means, before.means, rtol=0, atol=1e-6)
            torch.testing.assert_close(after.log_scales, before.log_scales, rtol=0, atol=1e-6)
            torch.testing.assert_close(after.rotations, before.rotations, rtol=0, atol=1e-6)
    with torch.no_grad():
        moved = (upgraded.deform(TIMES[-1], "fine").means - upgraded.deform(0.0, "fine").means).norm(dim=-1)
    assert float(moved[~dynamic].max()) > 0  # static Gaussians keep their (small) 4DGS motion


def test_with_the_triplane_decoder_the_upgrade_equals_the_plain_one(folder):
    hidden = hidden_args()
    plain, triplane = _load(folder, hidden, separated=True), _load_with(folder, hidden, "triplane")
    for model in (plain, triplane):
        upgrade_4dgs_model(model, TIMES, THRESHOLD, extent=1.0, bake=True)
    assert torch.equal(plain.deformation_table, triplane.deformation_table)
    with torch.no_grad():
        for t in TIMES[::3]:
            torch.testing.assert_close(triplane.deform(t, "fine").means, plain.deform(t, "fine").means,
                                       rtol=0, atol=1e-6)


def test_a_state_with_part_of_the_static_field_is_refused(folder, tmp_path):
    broken = tmp_path / "point_cloud" / "iteration_1"
    broken.mkdir(parents=True)
    (broken / "point_cloud.ply").write_bytes((folder / "point_cloud.ply").read_bytes())
    state = torch.load(folder / "deformation.pth")
    state["static_field.deformation_net.pos_deform.3.bias"] = state["deformation_net.pos_deform.3.bias"]
    torch.save(state, broken / "deformation.pth")
    with pytest.raises(ValueError, match="missing: static_field"):
        _load_with(broken, hidden_args(), "field")
