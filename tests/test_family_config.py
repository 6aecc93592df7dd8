"""A run without --configs gets its dataset family's config (baselines/fourdgs/family_config.py)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from baselines.data.errors import DatasetError
from baselines.fourdgs.family_config import CONFIG_ROOT, default_config, strip_bare_defaults


def _nvidia(root: Path) -> Path:
    (root / "images").mkdir(parents=True)
    np.save(root / "poses_bounds.npy", np.zeros((2, 17)))
    return root


def _family_folder(tmp_path: Path, family: str) -> Path:
    root = tmp_path / family
    if family == "nvidia":
        return _nvidia(root)
    root.mkdir()
    if family == "synthetic":
        _nvidia(root / "x")
        root = root / "x"
        (root / "scene.json").write_text(json.dumps({"simulator_version": "1.0", "name": "x"}))
    elif family == "hypernerf":
        (root / "dataset.json").write_text("{}")
        (root / "scene.json").write_text(json.dumps({"scale": 1.0, "center": [0, 0, 0]}))
    elif family == "dnerf":
        (root / "transforms_train.json").write_text("{}")
    elif family == "colmap":
        (root / "sparse" / "0").mkdir(parents=True)
        (root / "sparse" / "0" / "cameras.txt").write_text("")
    return root


@pytest.mark.parametrize("family, expected", [
    ("synthetic", "synthetic/default.py"), ("nvidia", "nvidia/default.py"),
    ("hypernerf", "hypernerf/default.py"), ("dnerf", "dnerf/dnerf_default.py"),
    ("colmap", "hypernerf/default.py"),
])
def test_each_family_gets_its_config(tmp_path, family, expected):
    decision = default_config(_family_folder(tmp_path, family), [])
    assert decision.family == family
    assert decision.path == CONFIG_ROOT / expected
    assert decision.path.is_file()


def test_plugin_family_file_preferred_when_it_exists(tmp_path):
    source = _family_folder(tmp_path, "nvidia")
    assert default_config(source, ["reflow"]).path == CONFIG_ROOT / "nvidia" / "reflow.py"
    # D-NeRF has no reflow file: the family default, not a missing file
    assert default_config(_family_folder(tmp_path, "dnerf"), ["reflow"]).path == CONFIG_ROOT / "dnerf" / "dnerf_default.py"
    # two plugins: no plugin-specific file is guessed
    assert default_config(source, ["reflow", "other"]).path == CONFIG_ROOT / "nvidia" / "default.py"


def test_dataset_type_overrides_detection(tmp_path):
    source = _family_folder(tmp_path, "nvidia")
    assert default_config(source, [], dataset_type="dnerf").family == "dnerf"


def test_missing_folder_is_a_dataset_error(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        default_config(tmp_path / "nowhere", [])


@pytest.mark.parametrize("argv, rest, bare", [
    (["-s", "x", "--configs", "none", "--iterations", "5"], ["-s", "x", "--iterations", "5"], True),
    (["--configs=NONE"], [], True),
    (["--configs", "a.py"], ["--configs", "a.py"], False),
    (["-s", "none"], ["-s", "none"], False),
])
def test_bare_defaults_flag(argv, rest, bare):
    assert strip_bare_defaults(argv) == (rest, bare)


def test_train_records_the_family_config(tmp_path, tiny_scene):
    """Through build_trainer: no --configs on a simulator scene -> synthetic config, in config.json."""
    from baselines.fourdgs.app import build_trainer

    scene = tiny_scene
    trainer = build_trainer(["-s", str(scene), "-m", str(tmp_path / "run"), "--iterations", "2",
                             "--coarse_iterations", "1", "--quiet"])
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["_default_config"]["family"] == "synthetic"
    assert config["_default_config"]["path"].endswith("synthetic/default.py")
    # the synthetic config's HexPlane, not 4DGS's bare 32-channel default
    assert trainer.args.hidden.kplanes_config["output_coordinate_dim"] == 16
    bare = build_trainer(["-s", str(scene), "-m", str(tmp_path / "bare"), "--configs", "none", "--quiet"])
    assert json.loads((tmp_path / "bare" / "config.json").read_text())["_default_config"] is None
    assert bare.args.hidden.kplanes_config["output_coordinate_dim"] == 32


def test_background_follows_the_family_unless_set(tmp_path, tiny_scene):
    """Real-capture families render on black, simulator scenes keep white; -w or a config wins."""
    import shutil

    from baselines.fourdgs.app import build_trainer

    capture = tmp_path / "capture"  # the same files without the simulator's scene.json: an NVIDIA capture
    shutil.copytree(tiny_scene, capture, ignore=shutil.ignore_patterns("scene.json"))
    run = ["--quiet", "--iterations", "1", "--coarse_iterations", "1"]
    assert build_trainer(["-s", str(tiny_scene), "-m", str(tmp_path / "a"), *run]).args.model.white_background
    black = build_trainer(["-s", str(capture), "-m", str(tmp_path / "b"), *run])
    assert not black.args.model.white_background
    assert black.ctx.background.tolist() == [0.0, 0.0, 0.0]
    saved = json.loads((tmp_path / "b" / "config.json").read_text())
    assert saved["ModelParams"]["white_background"] is False  # render.py sees the same
    assert build_trainer(["-s", str(capture), "-m", str(tmp_path / "c"), "-w", *run]).args.model.white_background
