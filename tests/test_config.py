"""Config files: precedence, _base_ chains, nested dict merge, errors, shipped files."""
from __future__ import annotations

import logging
from importlib.metadata import entry_points
from pathlib import Path

import pytest

from arguments import ConfigError, parse_train_args
from baselines.fourdgs.plugins import load_plugin_class

REPO = Path(__file__).resolve().parent.parent


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_precedence_default_base_child_second_file_cli(tmp_path):
    # each field is last set at a different level, so each level's win is visible
    write(tmp_path / "base.py",
          "OptimizationParams = dict(iterations=100, coarse_iterations=10, batch_size=3,"
          " feature_lr=0.5)\n")
    child = write(tmp_path / "cfg" / "child.py",
                  "_base_ = '../base.py'\n"
                  "OptimizationParams = dict(coarse_iterations=20, batch_size=4, feature_lr=0.6)\n")
    second = write(tmp_path / "second.py", "OptimizationParams = dict(batch_size=5, feature_lr=0.7)\n")
    args = parse_train_args(["--configs", str(child), str(second), "--feature_lr", "0.8"])
    opt = args.opt
    assert opt.opacity_lr == 0.05  # dataclass default (4DGS's)
    assert opt.iterations == 100  # base only
    assert opt.coarse_iterations == 20  # child over base
    assert opt.batch_size == 5  # second file over child
    assert opt.feature_lr == 0.8  # command line over everything
    src = args.sources
    assert src["OptimizationParams.opacity_lr"] == "default"
    assert src["OptimizationParams.iterations"] == str((tmp_path / "base.py").resolve())
    assert src["OptimizationParams.coarse_iterations"] == str(child.resolve())
    assert src["OptimizationParams.batch_size"] == str(second.resolve())
    assert src["OptimizationParams.feature_lr"] == "command line"


def test_untyped_flags_do_not_clobber_config_values(tmp_path):
    # argparse defaults must not override: eval=False and iterations from the file survive
    cfg = write(tmp_path / "c.py", "ModelParams = dict(eval=False)\n"
                                   "OptimizationParams = dict(iterations=7)\n")
    args = parse_train_args(["--configs", str(cfg), "-s", str(tmp_path)])
    assert args.model.eval is False and args.opt.iterations == 7


def test_configs_flag_repeatable(tmp_path):
    a = write(tmp_path / "a.py", "OptimizationParams = dict(iterations=1, batch_size=1)\n")
    b = write(tmp_path / "b.py", "OptimizationParams = dict(iterations=2)\n")
    args = parse_train_args(["--configs", str(a), "--configs", str(b)])
    assert args.opt.iterations == 2 and args.opt.batch_size == 1
    assert args.run.configs == [str(a), str(b)]


def test_base_chain_merges_nested_dicts_and_replaces_lists(tmp_path):
    write(tmp_path / "grand.py",
          "ModelHiddenParams = dict(kplanes_config=dict(output_coordinate_dim=16,"
          " resolution=[8, 8, 8, 4]), multires=[1, 2, 4])\n")
    write(tmp_path / "base.py", "_base_ = './grand.py'\n"
                                "ModelHiddenParams = dict(kplanes_config={'grid_dimensions': 2})\n")
    child = write(tmp_path / "child.py",
                  "_base_ = 'base.py'\n"
                  "ModelHiddenParams = dict(kplanes_config={'resolution': [16, 16, 16, 9]},"
                  " multires=[1])\n")
    hidden = parse_train_args(["--configs", str(child)]).hidden
    assert hidden.kplanes_config == {"grid_dimensions": 2, "input_coordinate_dim": 4,
                                     "output_coordinate_dim": 16, "resolution": [16, 16, 16, 9]}
    assert hidden.multires == [1]  # lists are replaced, not merged


def test_delete_replaces_dict_instead_of_merging(tmp_path):
    write(tmp_path / "base.py",
          "ModelHiddenParams = dict(kplanes_config=dict(output_coordinate_dim=16))\n"
          "OptimizationParams = dict(iterations=5, batch_size=2)\n")
    child = write(tmp_path / "child.py",
                  "_base_ = './base.py'\n"
                  "ModelHiddenParams = dict(kplanes_config=dict(_delete_=True, grid_dimensions=2,"
                  " input_coordinate_dim=3, output_coordinate_dim=8, resolution=[4, 4, 4]))\n"
                  "OptimizationParams = dict(_delete_=True, iterations=9)\n")
    args = parse_train_args(["--configs", str(child)])
    assert args.hidden.kplanes_config == {"grid_dimensions": 2, "input_coordinate_dim": 3,
                                          "output_coordinate_dim": 8, "resolution": [4, 4, 4]}
    assert args.opt.iterations == 9
    assert args.opt.batch_size == 1  # the group _delete_ dropped the base's value
    # without _delete_, a partial dict from the command line merges onto the configured one
    args = parse_train_args(["--configs", str(child), "--kplanes_config", "{'resolution': [5, 5, 5]}"])
    assert args.hidden.kplanes_config["input_coordinate_dim"] == 3
    assert args.hidden.kplanes_config["resolution"] == [5, 5, 5]


def test_base_list_applies_in_order(tmp_path):
    write(tmp_path / "a.py", "OptimizationParams = dict(iterations=1, batch_size=1)\n")
    write(tmp_path / "b.py", "OptimizationParams = dict(iterations=2)\n")
    child = write(tmp_path / "c.py", "_base_ = ['a.py', 'b.py']\n")
    opt = parse_train_args(["--configs", str(child)]).opt
    assert (opt.iterations, opt.batch_size) == (2, 1)


def test_lossless_coercions_and_helpers(tmp_path):
    cfg = write(tmp_path / "c.py",
                "import math\n"
                "_res = 32\n"
                "OptimizationParams = dict(feature_lr=1, iterations=2e3)\n"
                "ModelHiddenParams = dict(multires=(1, 2),"
                " kplanes_config={'resolution': [_res, _res, _res, 6]})\n")
    args = parse_train_args(["--configs", str(cfg)])
    assert args.opt.feature_lr == 1.0 and isinstance(args.opt.feature_lr, float)
    assert args.opt.iterations == 2000 and isinstance(args.opt.iterations, int)
    assert args.hidden.multires == [1, 2]
    assert args.hidden.kplanes_config["resolution"] == [32, 32, 32, 6]


def test_json_config_files(tmp_path):
    cfg = write(tmp_path / "c.json", '{"_note": "ignored", "OptimizationParams": {"iterations": 4},'
                                     ' "RunParams": {"test_iterations": [2, 4]}}')
    args = parse_train_args(["--configs", str(cfg)])
    assert args.opt.iterations == 4 and args.run.test_iterations == [2, 4]


def test_4dgs_misplaced_fields_land_in_their_group(tmp_path, caplog):
    # 4DGS flattens groups: its hypernerf scene files put kplanes_config under ModelParams,
    # its dnerf default puts render_process under OptimizationParams
    write(tmp_path / "default.py",
          "ModelHiddenParams = dict(kplanes_config={'grid_dimensions': 2, 'input_coordinate_dim': 4,"
          " 'output_coordinate_dim': 16, 'resolution': [64, 64, 64, 150]})\n"
          "OptimizationParams = dict(render_process=False, iterations=14000)\n")
    scene = write(tmp_path / "scene.py",
                  "_base_ = 'default.py'\n"
                  "ModelParams = dict(kplanes_config={'grid_dimensions': 2, 'input_coordinate_dim': 4,"
                  " 'output_coordinate_dim': 16, 'resolution': [64, 64, 64, 100]})\n"
                  "OptimizationParams = dict()\n")
    args = parse_train_args(["--configs", str(scene)])
    assert args.hidden.kplanes_config["resolution"] == [64, 64, 64, 100]
    assert args.model.render_process is False and args.opt.iterations == 14000


def test_same_field_under_two_groups_is_an_error(tmp_path):
    cfg = write(tmp_path / "c.py", "ModelParams = dict(iterations=3)\n"
                                   "OptimizationParams = dict(iterations=4)\n")
    with pytest.raises(ConfigError) as exc:
        parse_train_args(["--configs", str(cfg)])
    assert exc.value.file == str(cfg.resolve()) and "iterations" in exc.value.key


# --- every ConfigError path names the file and the key ---------------------------------------

ERROR_CASES = {
    "unknown group": ("OptimisationParams = dict(iterations=1)\n", "OptimisationParams",
                      "did you mean 'OptimizationParams'"),
    "unknown field": ("OptimizationParams = dict(iteratons=1)\n", "OptimizationParams.iteratons",
                      "did you mean 'iterations'"),
    "str for int": ("OptimizationParams = dict(iterations='10')\n", "OptimizationParams.iterations",
                    "expected int"),
    "lossy float for int": ("OptimizationParams = dict(iterations=1.5)\n",
                            "OptimizationParams.iterations", "expected int"),
    "bool for int": ("OptimizationParams = dict(batch_size=True)\n",
                     "OptimizationParams.batch_size", "expected int"),
    "int for bool": ("ModelParams = dict(eval=1)\n", "ModelParams.eval", "expected bool"),
    "bad list item": ("ModelHiddenParams = dict(multires=[1, 'x'])\n", "ModelHiddenParams.multires",
                      "int items"),
    "dict for list": ("ModelHiddenParams = dict(multires={'a': 1})\n",
                      "ModelHiddenParams.multires", "expected list"),
    "bad choice": ("PipelineParams = dict(backend='opengl')\n", "PipelineParams.backend",
                   "expected one of"),
    "failed check": ("PipelineParams = dict(device='gpu0')\n", "PipelineParams.device",
                     "cuda:N"),
    "group not a dict": ("OptimizationParams = 3\n", "OptimizationParams", "must be a dict"),
    "configs in a file": ("RunParams = dict(configs=['x.py'])\n", "RunParams.configs", "_base_"),
    "overwrite in a file": ("RunParams = dict(overwrite=True)\n", "RunParams.overwrite", "type --overwrite"),
    "merged dict check": ("ModelHiddenParams = dict(kplanes_config={'resolutions': [1]})\n",
                          "ModelHiddenParams.kplanes_config", "resolutions"),
    "bad _base_ type": ("_base_ = 3\n", "_base_", "_base_"),
}


@pytest.mark.parametrize("case", sorted(ERROR_CASES))
def test_config_errors_name_file_and_key(tmp_path, case):
    text, key, detail = ERROR_CASES[case]
    cfg = write(tmp_path / "bad.py", text)
    with pytest.raises(ConfigError) as exc:
        parse_train_args(["--configs", str(cfg)])
    err = exc.value
    assert err.file == str(cfg.resolve()) and err.key == key
    assert str(cfg.resolve()) in str(err) and key in str(err) and detail in str(err)


def test_missing_config_file(tmp_path):
    missing = tmp_path / "nope.py"
    with pytest.raises(ConfigError, match="config file not found") as exc:
        parse_train_args(["--configs", str(missing)])
    assert exc.value.file == str(missing) and "--configs" in str(exc.value)


def test_missing_base_names_the_referring_file(tmp_path):
    child = write(tmp_path / "child.py", "_base_ = './gone.py'\n")
    with pytest.raises(ConfigError) as exc:
        parse_train_args(["--configs", str(child)])
    err = exc.value
    assert err.key == "_base_" and err.file == str(tmp_path / "gone.py")
    assert str(child.resolve()) in str(err)


def test_syntax_error_reports_line(tmp_path):
    cfg = write(tmp_path / "bad.py", "OptimizationParams = dict(\n    iterations=1,\n    )\n)\n")
    with pytest.raises(ConfigError, match=r"bad\.py:4: syntax error") as exc:
        parse_train_args(["--configs", str(cfg)])
    assert exc.value.file == str(cfg.resolve())


def test_execution_error_reports_line(tmp_path):
    cfg = write(tmp_path / "bad.py", "x = 1\nOptimizationParams = dict(iterations=undefined)\n")
    with pytest.raises(ConfigError, match=r"bad\.py:2: error while executing: NameError"):
        parse_train_args(["--configs", str(cfg)])


@pytest.mark.parametrize("self_cycle", [False, True])
def test_base_cycle(tmp_path, self_cycle):
    if self_cycle:
        start = write(tmp_path / "a.py", "_base_ = 'a.py'\n")
    else:
        start = write(tmp_path / "a.py", "_base_ = 'b.py'\n")
        write(tmp_path / "b.py", "_base_ = ['a.py']\n")
    with pytest.raises(ConfigError, match="_base_ cycle") as exc:
        parse_train_args(["--configs", str(start)])
    assert exc.value.key == "_base_" and "a.py -> " in str(exc.value)


# --- shipped config files ---------------------------------------------------------------------

SHIPPED = sorted((REPO / "arguments").glob("*/*.py"))
PLUGINS = {ep.name for ep in entry_points(group="fourdgs.plugins")}


def test_shipped_configs_exist():
    names = {p.relative_to(REPO / "arguments").as_posix() for p in SHIPPED}
    assert {"dnerf/dnerf_default.py", "dnerf/lego.py", "hypernerf/default.py",
            "nvidia/default.py", "synthetic/default.py"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_shipped_config_loads_without_warnings(path, caplog):
    # A plugin's config (arguments/<family>/<plugin>.py) carries the plugin's group: parse it
    # with that group, as train.py does after --plugin NAME.
    extra = load_plugin_class(path.stem).param_groups if path.stem in PLUGINS else None
    with caplog.at_level(logging.WARNING, logger="arguments"):
        args = parse_train_args(["--configs", str(path)], extra_groups=extra)
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    opt = args.opt
    assert 0 < opt.coarse_iterations < opt.iterations
    assert opt.densify_from_iter < opt.densify_until_iter <= opt.iterations
    res = args.hidden.kplanes_config["resolution"]
    assert len(res) == 4


def test_shipped_values_match_4dgs():
    lego = parse_train_args(["--configs", str(REPO / "arguments/dnerf/lego.py")])
    assert lego.opt.iterations == 20000 and lego.opt.pruning_interval == 8000
    assert lego.opt.grid_lr_final == 0.000016 and lego.opt.deformation_lr_final == 0.0000016
    assert lego.hidden.kplanes_config == {"grid_dimensions": 2, "input_coordinate_dim": 4,
                                          "output_coordinate_dim": 32,
                                          "resolution": [64, 64, 64, 25]}
    assert lego.hidden.multires == [1, 2] and lego.hidden.defor_depth == 0
    hyper = parse_train_args(["--configs", str(REPO / "arguments/hypernerf/chicken.py")])
    assert hyper.opt.iterations == 14000 and hyper.opt.batch_size == 2
    assert hyper.hidden.kplanes_config["resolution"] == [64, 64, 64, 80]
    assert hyper.hidden.kplanes_config["output_coordinate_dim"] == 16
    assert hyper.hidden.net_width == 128 and hyper.hidden.multires == [1, 2, 4]
    synth = parse_train_args(["--configs", str(REPO / "arguments/synthetic/default.py")])
    assert synth.opt.iterations <= 5000 and synth.opt.coarse_iterations <= 500
    assert synth.hidden.kplanes_config["resolution"] == [32, 32, 32, 12]
    assert synth.hidden.multires == [1, 2]
    assert max(synth.run.test_iterations + synth.run.save_iterations) <= synth.opt.iterations


# --- fields a group removed: one line saying so, not "unknown field" ---------------------------

def test_removed_reflow_field_in_a_config_file_says_it_was_removed(tmp_path):
    from reflow_plugin.params import ReFlowParams

    groups = {"ReFlowParams": ReFlowParams}
    cfg = write(tmp_path / "old.py", "ReFlowParams = dict(lambda_ff=1.0, relabel_every=100)\n")
    with pytest.raises(ConfigError) as exc:
        parse_train_args(["--configs", str(cfg)], extra_groups=groups)
    message = str(exc.value)
    assert exc.value.key == "ReFlowParams.relabel_every" and "\n" not in message
    assert "ReFlowParams.relabel_every was removed on 2026-11-26" in message and "docs/PARAMETERS.md" in message
    # a key that never existed is still an unknown field, with its close matches
    cfg = write(tmp_path / "typo.py", "ReFlowParams = dict(lambda_fff=1.0)\n")
    with pytest.raises(ConfigError, match=r"unknown field 'ReFlowParams.lambda_fff' \(did you mean 'lambda_ff'"):
        parse_train_args(["--configs", str(cfg)], extra_groups=groups)


@pytest.mark.parametrize("argv", [["--box_labels"], ["--no-anchor_keyframes"], ["--window_cull=0"],
                                  ["--iterations", "3", "--promote_residual", "3"]])
def test_removed_reflow_flag_on_the_command_line_says_it_was_removed(argv, capsys):
    from reflow_plugin.params import ReFlowParams

    with pytest.raises(SystemExit) as exc:
        parse_train_args(argv, extra_groups={"ReFlowParams": ReFlowParams})
    assert exc.value.code == 2
    err = capsys.readouterr().err
    name = argv[-1 if len(argv) == 1 else -2].split("=")[0].lstrip("-").removeprefix("no-")
    assert f"ReFlowParams.{name} was removed on 2026-11-26" in err
    # without the plugin's group the same flag is an ordinary unrecognized argument
    with pytest.raises(SystemExit):
        parse_train_args(argv)
    err = capsys.readouterr().err
    assert "unrecognized arguments" in err and "was removed" not in err


def test_removed_fields_are_not_fields_and_every_flag_has_a_row_in_the_parameter_doc():
    import dataclasses

    from reflow_plugin.params import ReFlowParams

    fields = [f.name for f in dataclasses.fields(ReFlowParams)]
    assert len(fields) <= 40
    assert not set(fields) & set(ReFlowParams.REMOVED_FIELDS)
    doc = (Path(__file__).resolve().parent.parent / "docs" / "PARAMETERS.md").read_text()
    kept, _, gone = doc.partition("## Fixed values")
    missing = [f for f in fields if f"`--{f}`" not in kept]
    assert not missing, f"flags without a row in docs/PARAMETERS.md: {missing}"
    undocumented = [f for f in ReFlowParams.REMOVED_FIELDS if f"--{f}" not in gone and f"--no-{f}" not in gone]
    assert not undocumented, f"removed fields without a row in docs/PARAMETERS.md: {undocumented}"
