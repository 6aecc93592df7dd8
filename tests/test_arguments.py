"""Parameter groups, command-line parsing, plugins' groups, cfg_args round trip."""
from __future__ import annotations

import argparse
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import pytest

from arguments import (ConfigError, ModelHiddenParams, ModelParams, OptimizationParams,
                       PipelineParams, group_fields, param, parse_render_args, parse_train_args,
                       peek_plugins, write_cfg_args)

# 4DGS's field names (hustvl/4DGaussians arguments/__init__.py), with a sample of its defaults
FOURDGS_FIELDS = {
    ModelParams: "sh_degree source_path model_path images resolution white_background data_device "
                 "eval render_process add_points extension llffhold",
    PipelineParams: "convert_SHs_python compute_cov3D_python debug",
    ModelHiddenParams: "net_width timebase_pe defor_depth posebase_pe scale_rotation_pe opacity_pe "
                       "timenet_width timenet_output bounds plane_tv_weight time_smoothness_weight "
                       "l1_time_planes kplanes_config multires no_dx no_grid no_ds no_dr no_do "
                       "no_dshs empty_voxel grid_pe static_mlp apply_rotation",
    OptimizationParams: "dataloader zerostamp_init custom_sampler iterations coarse_iterations "
                        "position_lr_init position_lr_final position_lr_delay_mult "
                        "position_lr_max_steps deformation_lr_init deformation_lr_final "
                        "deformation_lr_delay_mult grid_lr_init grid_lr_final feature_lr "
                        "opacity_lr scaling_lr rotation_lr percent_dense lambda_dssim "
                        "lambda_lpips weight_constraint_init weight_constraint_after "
                        "weight_decay_iteration opacity_reset_interval densification_interval "
                        "densify_from_iter densify_until_iter densify_grad_threshold_coarse "
                        "densify_grad_threshold_fine_init densify_grad_threshold_after "
                        "pruning_from_iter pruning_interval opacity_threshold_coarse "
                        "opacity_threshold_fine_init opacity_threshold_fine_after batch_size "
                        "add_point",
}
OURS = {ModelParams: {"dataset_type", "force_dataset_points", "train_cameras", "test_cameras", "test_every"}, PipelineParams: {"backend", "device", "time_outside"},
        OptimizationParams: {"seed", "densify_max_gaussians", "prune_min_gaussians",
                             "densify_grad_from", "stall_iterations",
                             "nonfinite_skips"},
        ModelHiddenParams: {"mlp_precision"}}


@pytest.mark.parametrize("cls", list(FOURDGS_FIELDS), ids=lambda c: c.__name__)
def test_groups_have_exactly_4dgs_fields_plus_ours(cls):
    specs = group_fields(cls)
    assert set(specs) == set(FOURDGS_FIELDS[cls].split()) | OURS[cls]
    assert {n for n, s in specs.items() if s.ours} == OURS[cls]
    assert all(s.help for s in specs.values())


def test_4dgs_defaults():
    args = parse_train_args([])
    m, h, o = args.model, args.hidden, args.opt
    assert (m.sh_degree, m.white_background, m.eval, m.resolution, m.llffhold) == (3, True, True, -1, 8)
    assert (h.net_width, h.defor_depth, h.bounds, h.multires) == (64, 1, 1.6, [1, 2, 4, 8])
    assert h.kplanes_config["resolution"] == [64, 64, 64, 25] and (h.no_do, h.no_dshs) == (True, True)
    assert (o.iterations, o.coarse_iterations, o.densify_until_iter) == (30000, 3000, 15000)
    assert (o.position_lr_init, o.grid_lr_final, o.opacity_lr) == (0.00016, 0.00016, 0.05)
    assert args.run.test_iterations == [3000, 7000, 14000] and args.run.port == 6009
    assert args.run.start_checkpoint is None and args.run.checkpoint_iterations == []
    assert (args.pipe.backend, args.pipe.device, m.dataset_type, o.seed) == ("auto", "auto", "auto", 0)


def test_defaults_are_not_shared_between_instances():
    a, b = ModelHiddenParams(), ModelHiddenParams()
    a.kplanes_config["resolution"][0] = 1
    a.multires.append(16)
    assert b.kplanes_config["resolution"][0] == 64 and b.multires == [1, 2, 4, 8]


def test_4dgs_short_flags():
    args = parse_train_args(["-s", "data/x", "-m", "out/y", "-i", "imgs", "-r", "2"])
    assert Path(args.model.source_path) == Path("data/x").resolve()
    assert (args.model.model_path, args.model.images, args.model.resolution) == ("out/y", "imgs", 2)
    assert parse_train_args([]).model.source_path == ""  # empty = embedded synthetic scene


def test_bool_flags_switch_both_ways(tmp_path):
    assert parse_train_args(["--no-eval"]).model.eval is False
    assert parse_train_args(["--no-white_background"]).model.white_background is False
    assert parse_train_args(["--no-no_do"]).hidden.no_do is False
    assert parse_train_args(["--detect_anomaly"]).run.detect_anomaly is True
    cfg = tmp_path / "c.py"
    cfg.write_text("ModelParams = dict(eval=False, white_background=False)\n")
    args = parse_train_args(["--configs", str(cfg), "--eval", "-w"])
    assert args.model.eval is True and args.model.white_background is True


def test_list_and_dict_flags():
    args = parse_train_args(["--test_iterations", "10", "20", "--save_iterations", "[30]",
                             "--multires", "1", "2", "--checkpoint_iterations", "[]",
                             "--kplanes_config", "{'resolution': [8, 8, 8, 3]}"])
    assert args.run.test_iterations == [10, 20] and args.run.save_iterations == [30]
    assert args.hidden.multires == [1, 2] and args.run.checkpoint_iterations == []
    assert args.hidden.kplanes_config == {"grid_dimensions": 2, "input_coordinate_dim": 4,
                                          "output_coordinate_dim": 32, "resolution": [8, 8, 8, 3]}
    assert parse_train_args(["--multires", "[1, 2, 4]"]).hidden.multires == [1, 2, 4]


@pytest.mark.parametrize("argv, message", [
    (["--iterations", "abc"], "argument --iterations: expected int"),
    (["--multires", "1", "x"], "argument --multires: expected int"),
    (["--kplanes_config", "{'a': "], "argument --kplanes_config"),
    (["--backend", "opengl"], "invalid choice"),
    (["--device", "gpu"], "cuda:N"),
    (["--iteratons", "5"], "did you mean --iterations"),
    (["--no-evl"], "did you mean --no-eval"),
    (["--static_mlp"], "argument --static_mlp: is not supported"),      # 4DGS experiments this host does not run
    (["--empty_voxel"], "argument --empty_voxel: is not supported"),
    (["--grid_pe", "1"], "must be 0 (off) or > 1, got 1"),  # implemented: refused values only
])
def test_bad_flags_exit_with_a_clear_message(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        parse_train_args(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_plugin_disable_enable_lists():
    args = parse_train_args(["--plugin", "reflow,b", "--plugin", "c", "--disable", "full_flow, cam_flow",
                             "--enable", "fb_occlusion", "--log_every", "5"])
    assert args.run.plugin == ["reflow", "b", "c"]
    assert args.run.disable == ["full_flow", "cam_flow"] and args.run.enable == ["fb_occlusion"]
    assert args.run.log_every == 5


def test_compat_field_warns_once(tmp_path, caplog):
    base = tmp_path / "base.py"
    base.write_text("ModelParams = dict(data_device='cpu')\n")
    child = tmp_path / "child.py"
    child.write_text("_base_ = 'base.py'\nModelParams = dict(data_device='cuda:1')\n")
    with caplog.at_level(logging.WARNING, logger="arguments"):
        args = parse_train_args(["--configs", str(child), "--data_device", "cpu", "--port", "6009"])
    assert args.model.data_device == "cpu"
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 1, msgs  # port is compat-only too, but left at its default
    assert "ModelParams.data_device" in msgs[0] and "no effect" in msgs[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="arguments"):
        parse_train_args(["--backend", "cpu"])
    assert not caplog.records
    # flags that change the computation are not called "no effect" (grid_pe and apply_rotation are
    # implemented; the unused time network's size changes the random initial weights)...
    with caplog.at_level(logging.WARNING, logger="arguments"):
        parse_train_args(["--grid_pe", "2", "--apply_rotation", "--timenet_width", "8"])
    assert not caplog.records
    # ...and one that 4DGS never applies (no warm-up steps) is
    with caplog.at_level(logging.WARNING, logger="arguments"):
        parse_train_args(["--position_lr_delay_mult", "1.0"])
    assert "OptimizationParams.position_lr_delay_mult" in caplog.records[0].getMessage()


# --- plugins ----------------------------------------------------------------------------------

@dataclass
class FakeFlowParams:
    """A plugin's parameter group."""

    lambda_ff: float = param(5.0, "full-flow loss weight")
    flow_pairs: list[int] = param([1], "frame offsets of training pairs")
    use_occlusion: bool = param(True, "forward-backward occlusion masks")


def test_peek_plugins_forms(tmp_path):
    assert peek_plugins(["-s", "x", "--plugin", "a,b", "--iterations", "3", "--plugin=c"]) == ["a", "b", "c"]
    assert peek_plugins(["-s", "x", "--unknown", "1"]) == []
    # several names after one flag, as the full parser reads them (each is then loaded and checked)
    assert peek_plugins(["--plugin", "reflow", "nosuch", "-s", "x"]) == ["reflow", "nosuch"]
    assert parse_train_args(["--plugin", "a", "b", "-s", "x"]).run.plugin == ["a", "b"]
    cfg = tmp_path / "c.py"
    (tmp_path / "base.py").write_text("RunParams = dict(plugin=['fromfile'])\n")
    cfg.write_text("_base_ = 'base.py'\n")
    assert peek_plugins(["--configs", str(cfg)]) == ["fromfile"]
    assert peek_plugins(["--configs", str(cfg), "--plugin", "cli"]) == ["cli"]  # CLI wins
    # the full parse agrees with the peek
    assert parse_train_args(["--configs", str(cfg)]).run.plugin == ["fromfile"]


def test_extra_group_from_config_and_cli(tmp_path):
    cfg = tmp_path / "c.py"
    cfg.write_text("FakeFlowParams = dict(lambda_ff=1.0, flow_pairs=[1, 2])\n"
                   "OptimizationParams = dict(iterations=10)\n")
    extra = {"FakeFlowParams": FakeFlowParams}
    args = parse_train_args(["--configs", str(cfg), "--no-use_occlusion"], extra_groups=extra)
    flow = args.extra["FakeFlowParams"]
    assert isinstance(flow, FakeFlowParams)
    assert (flow.lambda_ff, flow.flow_pairs, flow.use_occlusion) == (1.0, [1, 2], False)
    assert args.opt.iterations == 10
    args = parse_train_args(["--configs", str(cfg), "--lambda_ff", "0.3"], extra_groups=extra)
    assert args.extra["FakeFlowParams"].lambda_ff == 0.3
    # without the plugin loaded, its section is an unknown group that points at --plugin
    with pytest.raises(ConfigError, match="--plugin") as exc:
        parse_train_args(["--configs", str(cfg)])
    assert exc.value.key == "FakeFlowParams"


def test_extra_group_name_clashes_are_programming_errors():
    @dataclass
    class Clash:
        iterations: int = param(1, "clashes with OptimizationParams.iterations")

    with pytest.raises(ValueError, match="iterations"):
        parse_train_args([], extra_groups={"Clash": Clash})
    with pytest.raises(ValueError, match="clash"):
        parse_train_args([], extra_groups={"ModelParams": FakeFlowParams})


# --- saved configuration and render arguments -------------------------------------------------

def test_cfg_args_round_trip_and_cli_wins(tmp_path):
    cfg = tmp_path / "c.py"
    cfg.write_text("ModelHiddenParams = dict(kplanes_config={'resolution': [16, 16, 16, 6]})\n"
                   "OptimizationParams = dict(iterations=123)\n")
    model_dir = tmp_path / "out"
    extra = {"FakeFlowParams": FakeFlowParams}
    train = parse_train_args(["--configs", str(cfg), "-s", str(tmp_path), "-m", str(model_dir),
                              "--sh_degree", "1", "--no-white_background", "--plugin", "fake",
                              "--lambda_ff", "2.5", "--backend", "cpu"], extra_groups=extra)
    cfg_path, json_path = write_cfg_args(model_dir, train)
    assert sorted(p.name for p in model_dir.iterdir()) == ["cfg_args", "config.json"]  # no temp left

    # 4DGS's format: a Namespace repr with every field, flattened
    ns = eval(cfg_path.read_text(), {"Namespace": argparse.Namespace})
    assert ns.iterations == 123 and ns.sh_degree == 1 and ns.lambda_ff == 2.5
    assert ns.kplanes_config["resolution"] == [16, 16, 16, 6] and ns.plugin == ["fake"]

    # config.json reproduces the run as a config file
    again = parse_train_args(["--configs", str(json_path)], extra_groups=extra)
    assert again.groups().keys() == train.groups().keys()
    for name, group in train.groups().items():
        if name != "RunParams":
            assert again.groups()[name] == group, name
    assert json.loads(json_path.read_text())["_sources"]["OptimizationParams.iterations"] == str(cfg.resolve())

    assert peek_plugins(["-m", str(model_dir)], from_model_dir=True) == ["fake"]
    render = parse_render_args(["-m", str(model_dir), "--iteration", "7000", "--skip_train",
                                "--sh_degree", "2", "--backend", "reference"], extra_groups=extra)
    assert render.hidden.kplanes_config["resolution"] == [16, 16, 16, 6]  # restored
    assert render.model.white_background is False and render.opt.iterations == 123
    assert render.extra["FakeFlowParams"].lambda_ff == 2.5 and render.run.plugin == ["fake"]
    assert render.model.sh_degree == 2 and render.pipe.backend == "reference"  # CLI wins
    assert (render.render.iteration, render.render.skip_train, render.render.skip_test) == (7000, True, False)

    # a 4DGS output directory has only cfg_args; --configs applies over it, the CLI over both
    json_path.unlink()
    over = tmp_path / "over.py"
    over.write_text("ModelParams = dict(sh_degree=0)\nOptimizationParams = dict(iterations=5)\n")
    render = parse_render_args(["-m", str(model_dir), "--configs", str(over), "--sh_degree", "3"],
                               extra_groups=extra)
    assert render.hidden.kplanes_config["resolution"] == [16, 16, 16, 6]
    assert render.opt.iterations == 5 and render.model.sh_degree == 3
    assert render.extra["FakeFlowParams"].lambda_ff == 2.5


def test_render_reads_a_4dgs_cfg_args(tmp_path):
    # keys 4DGS writes that have no field here (or are command-line only) are ignored
    (tmp_path / "cfg_args").write_text(
        "Namespace(add_points=False, bounds=1.6, configs='arguments/dnerf/lego.py', "
        "data_device='cuda', expname='dnerf/lego', extension='.png', ip='127.0.0.1', "
        "kplanes_config={'grid_dimensions': 2, 'input_coordinate_dim': 4, "
        "'output_coordinate_dim': 32, 'resolution': [64, 64, 64, 25]}, model_path='output/x', "
        "multires=[1, 2], render_process=False, sh_degree=3, source_path='data/lego', "
        "start_checkpoint=None, white_background=True, gui_extra=1)")
    render = parse_render_args(["-m", str(tmp_path)])
    assert render.hidden.multires == [1, 2] and render.run.expname == "dnerf/lego"
    assert render.model.model_path == str(tmp_path)  # the command line's -m wins
    assert Path(render.model.source_path) == Path("data/lego").resolve()


def test_render_errors(tmp_path, capsys):
    with pytest.raises(SystemExit):
        parse_render_args(["--iteration", "3"])
    assert "--model_path" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="model directory not found"):
        parse_render_args(["-m", str(tmp_path / "missing")])
    (tmp_path / "cfg_args").write_text("Namespace(sh_degree='three')")
    with pytest.raises(ConfigError) as exc:
        parse_render_args(["-m", str(tmp_path)])
    assert exc.value.key == "ModelParams.sh_degree" and "cfg_args" in exc.value.file
    (tmp_path / "cfg_args").write_text("__import__('os')")
    with pytest.raises(ConfigError, match="unreadable cfg_args"):
        parse_render_args(["-m", str(tmp_path)])


def test_help_names_the_family_background_and_render_s_saved_configuration(capsys):
    """--white_background's shown default (4DGS's True) is replaced by the dataset family's whenever no
    flag or config file sets it, --configs none included; render.py's values come from the model
    directory. The help said neither."""
    with pytest.raises(SystemExit):
        parse_train_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "unless a flag or config file sets it, the dataset family's" in text
    assert "--configs none keeps the defaults shown (the background excepted" in text
    with pytest.raises(SystemExit):
        parse_render_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "the model directory's saved configuration replaces them" in text


@pytest.mark.parametrize("argv, message", [
    (["--sh_degree", "4"], "argument --sh_degree: must be in [0, 3], got 4"),
    (["-r", "0"], "argument --resolution: expected -1, 1, 2, 4, 8 or a width > 0, got 0"),
    (["--resolution", "-2"], "argument --resolution: expected -1, 1, 2, 4, 8 or a width > 0, got -2"),
    (["--lambda_dssim", "-0.2"], "argument --lambda_dssim: must be >= 0, got -0.2"),
    (["--percent_dense", "-0.01"], "argument --percent_dense: must be >= 0"),
    (["--time_smoothness_weight", "-1"], "argument --time_smoothness_weight: must be >= 0"),
    (["--plane_tv_weight", "-1"], "argument --plane_tv_weight: must be >= 0"),
    (["--l1_time_planes", "-1"], "argument --l1_time_planes: must be >= 0"),
    (["--densify_grad_threshold_after", "-0.0001"], "argument --densify_grad_threshold_after: must be >= 0"),
    (["--opacity_threshold_fine_init", "1.5"], "argument --opacity_threshold_fine_init: must lie in [0, 1], got 1.5"),
    (["--opacity_threshold_coarse", "-0.1"], "argument --opacity_threshold_coarse: must lie in [0, 1]"),
])
def test_out_of_range_values_are_flag_errors(argv, message, capsys):
    """Values outside a flag's meaning were accepted: --sh_degree 4 trained until the active degree
    reached 4 (fine iteration 4000) and then stopped in the SH evaluation (render.py of such a run at
    once); -r 0 was refused by the reader only after the run folder was claimed, without the flag's
    name; negative loss weights, thresholds and an opacity threshold above 1 trained silently."""
    with pytest.raises(SystemExit) as exc:
        parse_train_args(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_sh_degree_limit_is_the_renderer_s():
    from arguments.params import MAX_SH_DEGREE
    from baselines.render.sh import MAX_SH_DEGREE as RENDERER_MAX

    assert MAX_SH_DEGREE == RENDERER_MAX
    assert parse_train_args(["--sh_degree", "0", "-r", "640"]).model.sh_degree == 0


def test_a_config_file_out_of_range_value_names_the_file_and_key(tmp_path):
    cfg = tmp_path / "c.py"
    cfg.write_text("ModelParams = dict(sh_degree=5)\n")
    with pytest.raises(ConfigError, match=r"c\.py: ModelParams\.sh_degree: must be in \[0, 3\], got 5"):
        parse_train_args(["--configs", str(cfg)])


def test_render_iteration_below_minus_one_is_refused(tmp_path, capsys):
    """--iteration -5 rendered the latest iteration, as -1 does, without a word."""
    with pytest.raises(SystemExit) as exc:
        parse_render_args(["-m", str(tmp_path), "--iteration", "-5"])
    assert exc.value.code == 2
    assert "argument --iteration: expected a saved iteration or -1 (the latest), got -5" in capsys.readouterr().err


def test_a_float_flag_takes_finite_numbers_only(tmp_path, capsys):
    """1e999 parsed as inf and passed every >= 0 check (an infinite loss weight trains to NaN); a config
    file's float('nan') passed every field without a check."""
    with pytest.raises(SystemExit):
        parse_train_args(["--lambda_dssim", "1e999"])
    assert "argument --lambda_dssim: expected a finite number, got inf" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_train_args(["--flow_blur_sigmas", "2", "1e999"], extra_groups=_reflow_groups())
    assert "argument --flow_blur_sigmas: expected a finite number, got inf" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_train_args(["--bounds", "1" + "0" * 400])
    assert "argument --bounds: expected a finite number, got inf" in capsys.readouterr().err
    cfg = tmp_path / "c.py"
    cfg.write_text("ModelHiddenParams = dict(bounds=float('nan'))\n")
    with pytest.raises(ConfigError, match=r"c\.py: ModelHiddenParams\.bounds: expected a finite number, got nan"):
        parse_train_args(["--configs", str(cfg)])
    assert parse_train_args(["--bounds", "2"]).hidden.bounds == 2.0


def _reflow_groups() -> dict[str, type]:
    from reflow_plugin.params import ReFlowParams

    return {"ReFlowParams": ReFlowParams}
