"""4DGS-layout checkpoints: PLY and state-dict round trips, 4DGS files, atomic writes, errors."""

import os

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from baselines.fourdgs.checkpoint import (
    FolderContentError,
    atomic_save,
    find_latest_iteration,
    gaussians_to_ply,
    load_point_cloud_dir,
    load_training_state,
    ply_attribute_names,
    point_cloud_dir,
    save_point_cloud_dir,
    save_training_state,
    training_state_path,
)
from baselines.fourdgs.gaussian_model import GaussianModel
from benchmarks.deformation import PlainDeformNetwork
from tests._model_helpers import hidden_args, make_model, opt_args


def _randomize(model, seed=0):
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in (model._xyz, model._features_dc, model._features_rest, model._scaling, model._rotation,
                      model._opacity, *model.deformation.parameters()):
            if param.requires_grad:
                param.copy_(torch.randn(param.shape, generator=generator))
    model._deformation_table = torch.rand(model.num_gaussians, generator=generator) > 0.5
    model._deformation_accum = torch.rand(model.num_gaussians, 3, generator=generator)


def test_point_cloud_dir_round_trip(tmp_path):
    model = make_model(count=25)
    _randomize(model)
    model.register_gaussian_buffer("is_dynamic", torch.arange(25) % 4 == 0)
    model.register_gaussian_parameter("weights", torch.randn(25, 3), lr=0.02)
    folder = point_cloud_dir(tmp_path, 700, "fine")
    save_point_cloud_dir(model, folder)
    assert sorted(os.listdir(folder)) == ["deformation.pth", "deformation_accum.pth", "deformation_table.pth",
                                          "extra_buffers.pth", "manifest.json", "point_cloud.ply"]

    loaded = GaussianModel(3, hidden_args())
    load_point_cloud_dir(folder, loaded)
    for name in ("_xyz", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity",
                 "_deformation_table", "_deformation_accum"):
        assert torch.equal(getattr(loaded, name), getattr(model, name)), name
    expected_state = model.deformation.state_dict()
    for key, value in loaded.deformation.state_dict().items():
        assert torch.equal(value, expected_state[key]), key
    assert torch.equal(loaded.registered_buffers["is_dynamic"], model.registered_buffers["is_dynamic"])
    assert torch.equal(loaded.registered_parameters["weights"], model.registered_parameters["weights"])
    assert loaded.registered_parameter_lrs["weights"] == 0.02
    assert loaded.active_sh_degree == 3 and loaded.optimizer is None
    assert find_latest_iteration(tmp_path, "fine") == 700 and find_latest_iteration(tmp_path, "coarse") is None


def test_ply_uses_4dgs_property_order_and_channel_major_sh():
    model = make_model(count=3, sh_degree=1)
    with torch.no_grad():
        model._features_rest.copy_(torch.arange(27.0).reshape(3, 3, 3))  # [N, K-1=3, RGB]
    ply = gaussians_to_ply(model)
    names = [p.name for p in ply["vertex"].properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(9)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    # channel-major: f_rest_0..2 are R of coefficients 1..3, then G, then B.
    row = ply["vertex"][1]
    assert [row[f"f_rest_{i}"] for i in range(9)] == [9.0, 12.0, 15.0, 10.0, 13.0, 16.0, 11.0, 14.0, 17.0]


def _write_4dgs_folder(folder, count, sh_degree, hidden, seed=0):
    """Files as 4DGS's save_ply / save_deformation write them (features built as 4DGS does)."""
    rng = np.random.default_rng(seed)
    coefficients = (sh_degree + 1) ** 2
    features = rng.normal(size=(count, 3, coefficients)).astype(np.float32)  # 4DGS: [P, 3, K]
    xyz = rng.normal(size=(count, 3)).astype(np.float32)
    opacity = rng.normal(size=(count, 1)).astype(np.float32)
    scale = rng.normal(size=(count, 3)).astype(np.float32)
    rotation = rng.normal(size=(count, 4)).astype(np.float32)
    f_dc = features[:, :, 0]
    f_rest = features[:, :, 1:].reshape(count, -1)  # == transpose(1, 2) of _features_rest, flattened
    attributes = np.concatenate((xyz, np.zeros_like(xyz), f_dc, f_rest, opacity, scale, rotation), axis=1)
    names = ply_attribute_names(coefficients - 1)
    elements = np.empty(count, dtype=[(n, "f4") for n in names])
    elements[:] = list(map(tuple, attributes))
    folder.mkdir(parents=True)
    PlyData([PlyElement.describe(elements, "vertex")]).write(str(folder / "point_cloud.ply"))
    torch.save(PlainDeformNetwork(hidden).state_dict(), folder / "deformation.pth")
    return features, xyz, opacity, scale, rotation


def test_loads_a_4dgs_folder_without_our_extra_files(tmp_path):
    hidden = hidden_args()
    folder = tmp_path / "point_cloud" / "iteration_3000"
    features, xyz, opacity, scale, rotation = _write_4dgs_folder(folder, 12, 3, hidden)
    model = GaussianModel(3, hidden)
    model.register_gaussian_buffer("stale", torch.zeros(0))
    load_point_cloud_dir(folder, model)
    np.testing.assert_array_equal(model._xyz.detach().numpy(), xyz)
    np.testing.assert_array_equal(model._features_dc.detach().numpy(), features[:, :, :1].transpose(0, 2, 1))
    np.testing.assert_array_equal(model._features_rest.detach().numpy(), features[:, :, 1:].transpose(0, 2, 1))
    np.testing.assert_array_equal(model._opacity.detach().numpy(), opacity)
    np.testing.assert_array_equal(model._scaling.detach().numpy(), scale)
    np.testing.assert_array_equal(model._rotation.detach().numpy(), rotation)
    assert model._deformation_table.all() and not model._deformation_accum.any()
    assert dict(model.registered_buffers) == {}
    # and the loaded model trains
    model.spatial_lr_scale = 1.0
    model.training_setup(opt_args())
    model.deform(0.5, "fine").means.sum().backward()
    model.optimizer.step()


def test_load_errors_name_the_file(tmp_path):
    hidden = hidden_args()
    folder = tmp_path / "it"
    _write_4dgs_folder(folder, 5, 2, hidden)
    with pytest.raises(ValueError, match=r"point_cloud\.ply.*SH degree 2.*SH degree 3"):
        load_point_cloud_dir(folder, GaussianModel(3, hidden))
    with pytest.raises(ValueError, match=r"deformation\.pth.*wrong shape: deformation_net\.feature_out\.0\.weight"):
        load_point_cloud_dir(folder, GaussianModel(2, hidden_args(net_width=8)))
    (folder / "deformation.pth").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match=r"deformation\.pth: cannot be read"):
        load_point_cloud_dir(folder, GaussianModel(2, hidden))
    (folder / "deformation.pth").unlink()
    with pytest.raises(ValueError, match=r"deformation\.pth: file not found"):
        load_point_cloud_dir(folder, GaussianModel(2, hidden))
    (folder / "point_cloud.ply").write_bytes(b"ply\ngarbage")
    with pytest.raises(ValueError, match=r"point_cloud\.ply: not a readable"):
        load_point_cloud_dir(folder, GaussianModel(2, hidden))
    with pytest.raises(ValueError, match="checkpoint folder not found"):
        load_point_cloud_dir(tmp_path / "missing", GaussianModel(2, hidden))


def test_non_finite_values_in_a_ply_are_a_damaged_file_not_a_config_mismatch(tmp_path):
    """NaN in a 4DGS folder's PLY (no manifest to catch it) is a `FolderContentError`: the callers
    (`--start_checkpoint`, render.py) then add no "pass --configs" hint, which no config answers."""
    hidden = hidden_args()
    folder = tmp_path / "it"
    _write_4dgs_folder(folder, 5, 2, hidden)
    ply = PlyData.read(str(folder / "point_cloud.ply"), mmap=False)
    ply["vertex"].data["scale_1"][3] = np.nan
    ply.write(str(folder / "point_cloud.ply"))
    with pytest.raises(FolderContentError, match=r"point_cloud\.ply: scaling values contain NaN or inf"):
        load_point_cloud_dir(folder, GaussianModel(2, hidden))


def test_mismatched_table_is_rejected_before_the_model_changes(tmp_path):
    model = make_model(count=8)
    save_point_cloud_dir(model, tmp_path)
    torch.save(torch.ones(7, dtype=torch.bool), tmp_path / "deformation_table.pth")
    target = make_model(count=3, seed=1)
    xyz_before = target._xyz.detach().clone()
    with pytest.raises(ValueError, match=r"deformation_table\.pth is not the file the run saved there"):
        load_point_cloud_dir(tmp_path, target)  # the manifest catches it first
    (tmp_path / "manifest.json").unlink()  # a folder without one (4DGS's): the shape check
    with pytest.raises(ValueError, match=r"deformation_table\.pth.*\[8\]"):
        load_point_cloud_dir(tmp_path, target)
    assert torch.equal(target._xyz, xyz_before)


class _ExplodingPickle:
    def __reduce__(self):
        raise RuntimeError("serialiser failed midway")


def test_atomic_save_keeps_old_file_when_writing_fails(tmp_path):
    path = tmp_path / "deformation.pth"
    atomic_save({"weights": torch.arange(5)}, path)
    with pytest.raises(RuntimeError, match="midway"):
        atomic_save({"big": torch.zeros(100_000), "bad": _ExplodingPickle()}, path)
    assert torch.equal(torch.load(path)["weights"], torch.arange(5))
    assert os.listdir(tmp_path) == ["deformation.pth"]  # no temporary file left behind


def test_training_state_round_trip_and_4dgs_format(tmp_path):
    model = make_model(count=10)
    model.deform(0.1, "fine").means.sum().backward()
    model.optimizer.step()
    path = training_state_path(tmp_path, "fine", 1234)
    save_training_state(path, model, 1234, "fine", extra={"rng": torch.get_rng_state(), "note": "x"})
    state = load_training_state(path)
    assert (state.iteration, state.stage, state.extra["note"], state.is_4dgs_format) == (1234, "fine", "x", False)
    restored = GaussianModel(3, hidden_args())
    restored.restore(state.capture, opt_args())
    assert torch.equal(restored._xyz, model._xyz)

    four_dgs = tmp_path / "chkpnt_coarse_3000.pth"
    torch.save((model.capture()[:14], 3000), four_dgs)
    state = load_training_state(four_dgs)
    assert (state.iteration, state.stage, state.is_4dgs_format) == (3000, "coarse", True)
    GaussianModel(3, hidden_args()).restore(state.capture, opt_args())

    broken = tmp_path / "chkpnt_fine_1.pth"
    broken.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match="chkpnt_fine_1.pth"):
        load_training_state(broken)
    torch.save({"something": 1}, broken)
    with pytest.raises(ValueError, match="neither"):
        load_training_state(broken)


def _write_4dgs_checkpoint(path, model, iteration):
    """As 4DGS's train.py: torch.save((gaussians.capture(), iteration)), numpy scalars inside.

    4DGS's learning rates come from get_expon_lr_func (numpy.float64) and its spatial_lr_scale
    from the cameras' radius (numpy.float32).
    """
    capture = list(model.capture()[:14])
    optimizer_state = capture[12]
    for group in optimizer_state["param_groups"]:
        group["lr"] = np.float64(group["lr"])
    capture[12], capture[13] = optimizer_state, np.float32(capture[13])
    torch.save((tuple(capture), iteration), path)


def test_4dgs_checkpoint_with_numpy_scalars_loads_without_trusting_pickles(tmp_path):
    model = make_model(count=10)
    model.deform(0.1, "fine").means.sum().backward()
    model.optimizer.step()
    path = tmp_path / "chkpnt_fine_7000.pth"
    _write_4dgs_checkpoint(path, model, 7000)
    with pytest.raises(Exception, match="scalar"):
        torch.load(path, weights_only=True)  # the failure 4DGS users met
    state = load_training_state(path)
    assert (state.iteration, state.stage, state.is_4dgs_format) == (7000, "fine", True)
    restored = GaussianModel(3, hidden_args())
    restored.restore(state.capture, opt_args())
    assert torch.equal(restored._xyz, model._xyz)

    # any other object stays refused
    torch.save(((tmp_path,), 1), tmp_path / "chkpnt_fine_1.pth")
    with pytest.raises(ValueError, match="chkpnt_fine_1.pth"):
        load_training_state(tmp_path / "chkpnt_fine_1.pth")
