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


def _time_cells_sampled(times: list[float], cells: int) -> set[int]:
    """The temporal cells bilinear sampling reads at `times` in [0, 1] (4DGS: the upper half of [-1, 1])."""
    out = set()
    for t in times:
        position = (t + 1.0) / 2.0 * (cells - 1)
        low = min(int(np.floor(position)), cells - 2)
        out |= {low, low + 1} if position > low else {low}
    return out


@pytest.mark.parametrize("config_cells, frames, expected", [
    (96, 12, 6), (150, 49, 25), (150, 60, 30), (12, 36, 12), (12, 24, 12), (150, 3, 2), (150, 1, 2), (75, 150, 75),
])
def test_time_cells_follow_half_the_frames_when_fewer(config_cells, frames, expected):
    from baselines.fourdgs.family_config import fit_time_cells

    assert fit_time_cells(config_cells, frames) == expected


def test_fitted_time_cells_put_held_out_times_on_trained_cells():
    """Why the rule: 12 frames, every 8th held out (0 and 8). On the NVIDIA file's 96 cells the held-out
    times read cells no training time reads (untrained: the deformation there is its initial value);
    on the fitted 6 every cell a held-out time reads is also read by training times."""
    from baselines.fourdgs.family_config import fit_time_cells

    times = [i / 11 for i in range(12)]
    held, train = [times[0], times[8]], [t for i, t in enumerate(times) if i % 8]
    assert _time_cells_sampled(held, 96) - _time_cells_sampled(train, 96)
    fitted = fit_time_cells(96, len(times))
    assert _time_cells_sampled(held, fitted) <= _time_cells_sampled(train, fitted)


def test_a_short_capture_gets_fitted_time_cells_unless_the_user_sets_them(tmp_path, tiny_scene):
    """Through build_trainer on a 12-frame NVIDIA capture: the family file's 96 time cells become 6 (in
    config.json, so render.py rebuilds the same model); --kplanes_config or --configs keep theirs."""
    import shutil

    from baselines.fourdgs.app import build_trainer

    capture = tmp_path / "capture"
    shutil.copytree(tiny_scene, capture, ignore=shutil.ignore_patterns("scene.json"))
    run = ["--quiet", "--iterations", "1", "--coarse_iterations", "1"]
    fitted = build_trainer(["-s", str(capture), "-m", str(tmp_path / "a"), *run])
    assert fitted.args.hidden.kplanes_config["resolution"] == [64, 64, 64, 6]
    saved = json.loads((tmp_path / "a" / "config.json").read_text())
    assert saved["ModelHiddenParams"]["kplanes_config"]["resolution"] == [64, 64, 64, 6]
    assert "fitted to 12 frames" in saved["_sources"]["ModelHiddenParams.kplanes_config"]
    fitted.build()
    time_plane = fitted.ctx.model.deformation.deformation_net.grid.grids[0][2]  # (x, t): [1, C, T, X]
    assert time_plane.shape[-2] == 6
    explicit = build_trainer(["-s", str(capture), "-m", str(tmp_path / "b"), *run,
                              "--kplanes_config", "{'resolution': [64, 64, 64, 96]}"])
    assert explicit.args.hidden.kplanes_config["resolution"][3] == 96
    configured = build_trainer(["-s", str(capture), "-m", str(tmp_path / "c"), *run,
                                "--configs", str(CONFIG_ROOT / "nvidia" / "default.py")])
    assert configured.args.hidden.kplanes_config["resolution"][3] == 96
