"""End-to-end tests of the 4DGS host: training quality, exact resume, plugins, CLI errors."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from baselines.fourdgs.app import REPO_ROOT, build_trainer, finish_run
from baselines.fourdgs.evaluate import evaluate_cameras
from baselines.fourdgs.plugins import PluginError, register_plugin, unregister_plugin
from tests.example_plugin import CountingDeformation, ToyPairPlugin

# Short schedules on the 32x32 scene; densification inside the window so resume covers it. On
# 32x32 images the per-Gaussian gradients are ~50x larger than on 4DGS's 800x800 ones, so the
# densification threshold is raised accordingly (4DGS's 0.0002 would multiply the Gaussians 25x).
FAST = [
    "--quiet", "--test_iterations", "[]", "--save_iterations", "[]", "--log_every", "5",
    "--densify_from_iter", "10", "--densification_interval", "15", "--pruning_from_iter", "10",
    "--pruning_interval", "15", "--prune_min_gaussians", "0", "--densify_grad_threshold_coarse", "0.001",
    "--densify_grad_threshold_fine_init", "0.001", "--densify_grad_threshold_after", "0.001",
]


def base_argv(scene: Path, out: Path, coarse: int, fine: int, *extra: str) -> list[str]:
    return ["-s", str(scene), "-m", str(out), "--configs", str(REPO_ROOT / "arguments/synthetic/default.py"),
            "--coarse_iterations", str(coarse), "--iterations", str(fine), *FAST, *extra]


def mean_psnr(trainer, stage: str) -> float:
    result = evaluate_cameras(trainer.ctx.model, trainer.test_cameras, stage, trainer.ctx.background, "cpu")
    return result.mean["PSNR"]


def test_training_beats_initial_render_on_heldout_views(tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setattr("baselines.fourdgs.trainer.Trainer.QUICK_EVAL_VIEWS", 1)  # intermediate: 1 view
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "run", 60, 240))
    trainer.build()
    assert trainer.test_cameras, "the tiny scene must have held-out frames (--eval)"
    before = mean_psnr(trainer, "coarse")
    result = trainer.train()
    after = mean_psnr(trainer, "fine")
    assert after > before + 2.0, (before, after)
    summary = finish_run(trainer, result)
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    method = f"ours_{result.final_iteration}"
    assert results[method]["PSNR"] == pytest.approx(after, abs=1e-4)
    assert (tmp_path / "run" / "point_cloud" / f"iteration_{result.final_iteration}" / "point_cloud.ply").is_file()
    assert (tmp_path / "run" / "test" / method / "renders" / "00000.png").is_file()
    assert summary.video is not None and summary.video.stat().st_size > 0
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    assert any(r["kind"] == "iter" and r["stage"] == "fine" for r in log)
    final_test = [r for r in log if r["kind"] == "test"][-1]  # the last printed [test] line
    assert final_test["iteration"] == result.final_iteration
    assert final_test["test_psnr"] == pytest.approx(results[method]["PSNR"], abs=1e-9)


def _final_params(trainer) -> dict[str, torch.Tensor]:
    m = trainer.ctx.model
    params = {"xyz": m._xyz, "scaling": m._scaling, "f_dc": m._features_dc, "opacity": m._opacity}
    params.update({f"def.{k}": v for k, v in m._deformation.state_dict().items()})
    return {k: v.detach().clone() for k, v in params.items()}


def test_resume_equals_uninterrupted_run(tiny_scene, tmp_path):
    whole = build_trainer(base_argv(tiny_scene, tmp_path / "a", 20, 40, "--checkpoint_iterations", "20"))
    whole.train()
    checkpoint = tmp_path / "a" / "chkpnt_fine_20.pth"
    assert checkpoint.is_file()
    resumed = build_trainer(base_argv(tiny_scene, tmp_path / "b", 20, 40, "--start_checkpoint", str(checkpoint)))
    resumed.train()
    a, b = _final_params(whole), _final_params(resumed)
    assert a.keys() == b.keys() and a["xyz"].shape == b["xyz"].shape
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6, msg=key)


@pytest.fixture
def toy_plugin():
    register_plugin(ToyPairPlugin)
    yield ToyPairPlugin
    unregister_plugin(ToyPairPlugin.name)


def test_example_plugin_uses_every_hook(tiny_scene, tmp_path, toy_plugin):
    argv = base_argv(tiny_scene, tmp_path / "toy", 20, 30, "--plugin", "toy_pairs", "--toy_warmup_iterations", "10",
                     "--toy_dynamic_weight", "0.01")
    trainer = build_trainer(argv)
    plugin = trainer.hooks.plugins[0]
    assert isinstance(plugin, ToyPairPlugin) and plugin.toy.toy_warmup_iterations == 10
    trainer.build()
    model = trainer.ctx.model
    assert trainer.ctx.point_cloud_source == "plugin" and model.num_gaussians == 300
    assert isinstance(model.deformation, CountingDeformation)

    seen: dict[str, object] = {}
    deform_before = {k: v.detach().clone() for k, v in model.deformation.state_dict().items()}

    def spy(ctx):
        if ctx.stage == "fine" and ctx.iteration == 5:
            seen["frozen_changed"] = any(not torch.equal(deform_before[k], v)
                                         for k, v in ctx.model.deformation.state_dict().items())
            seen["extras"] = {k: tuple(v.shape) for k, v in ctx.views[0].extras.items()}
            seen["losses"] = sorted(ctx.losses)
            seen["batch_frames"] = [c.frame_index for c in ctx.batch]

    plugin.on_iteration_end = lambda ctx, _orig=plugin.on_iteration_end: (spy(ctx), _orig(ctx))
    trainer.train()
    cam = trainer.train_cameras[0]
    assert seen["extras"] == {"dynamic": (cam.height, cam.width, 1), "displacement": (cam.height, cam.width, 2)}
    assert "toy_pairs/dynamic" in seen["losses"] and "l1" in seen["losses"]
    a, b = seen["batch_frames"]
    assert a < b and not any(a < c.frame_index < b for c in trainer.train_cameras)  # neighbouring frames
    assert seen["frozen_changed"] is False  # deformation frozen during the warm-up
    after = model.deformation.state_dict()
    assert any(not torch.equal(deform_before[k], after[k]) for k in deform_before)  # trained afterwards
    assert plugin.deformation_checked and model.deformation.calls > 0
    assert plugin.calls["post_densify"] > 0 and plugin.buffer_sizes_ok
    assert model.gaussian_buffers["is_dynamic"].shape == (model.num_gaussians, 1)
    assert plugin.calls["stage_start_coarse"] == 1 and plugin.calls["stage_start_fine"] == 1


def test_dynamic_channel_renders_the_buffer(tiny_scene, tmp_path, toy_plugin):
    """A flag of 1 on every Gaussian renders as alpha: the extra channel goes through the same pass."""
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "dyn", 1, 1, "--plugin", "toy_pairs"))
    trainer.build()
    model = trainer.ctx.model
    model.set_gaussian_buffer("is_dynamic", torch.ones(model.num_gaussians, 1))
    from baselines.fourdgs.renderer import composite_view, prepare_view

    view = prepare_view(model, trainer.train_cameras[0], "coarse", "cpu")
    composite_view(view, trainer.ctx.background, {"dynamic": model.gaussian_buffers["is_dynamic"]}, "cpu")
    torch.testing.assert_close(view.extras["dynamic"], view.alpha, rtol=1e-5, atol=1e-6)


def test_unknown_plugin_and_component_are_clear_errors(tiny_scene, tmp_path, toy_plugin):
    with pytest.raises(PluginError, match="unknown plugin 'nope'.*toy_pairs"):
        build_trainer(base_argv(tiny_scene, tmp_path / "x", 1, 1, "--plugin", "nope"))
    with pytest.raises(PluginError, match="unknown component 'flow'.*pairs"):
        build_trainer(base_argv(tiny_scene, tmp_path / "x", 1, 1, "--plugin", "toy_pairs", "--disable", "flow"))
    with pytest.raises(PluginError, match="unknown component"):
        build_trainer(base_argv(tiny_scene, tmp_path / "x", 1, 1, "--disable", "full_flow"))


def test_cli_reports_bad_inputs_in_one_line(tmp_path):
    missing = tmp_path / "no_such_scene"
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "train.py"), "-s", str(missing), "-m", str(tmp_path / "o")],
                          capture_output=True, text=True, cwd=REPO_ROOT)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "no_such_scene" in lines[0], proc.stderr
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "train.py"), "--plugin", "nope"],
                          capture_output=True, text=True, cwd=REPO_ROOT)
    assert proc.returncode == 2 and "unknown plugin 'nope'" in proc.stderr


@pytest.fixture(scope="module")
def trained_run(tiny_scene, tmp_path_factory):
    """A baseline run (no plugin) with its point_cloud/iteration_20 folder."""
    out = tmp_path_factory.mktemp("trained") / "run"
    result = build_trainer(base_argv(tiny_scene, out, 10, 20)).train()
    return out, result


def test_start_from_a_point_cloud_folder_upgrades_into_the_fine_stage(tiny_scene, tmp_path, trained_run, toy_plugin):
    from baselines.fourdgs.checkpoint import read_gaussian_ply

    out, result = trained_run
    folder = out / "point_cloud" / f"iteration_{result.final_iteration}"
    saved = read_gaussian_ply(folder / "point_cloud.ply", 3)
    argv = base_argv(tiny_scene, tmp_path / "up", 10, 5, "--start_checkpoint", str(folder), "--plugin", "toy_pairs",
                     "--disable", "custom_init,custom_deformation")
    trainer = build_trainer(argv)
    plugin = trainer.hooks.plugins[0]
    loaded: dict[str, torch.Tensor] = {}

    def on_load_spy(ctx, directory, _orig=plugin.on_load):
        loaded["xyz"] = ctx.model._xyz.detach().clone()
        _orig(ctx, directory)
        loaded["flags"] = ctx.model.gaussian_buffers["is_dynamic"]

    plugin.on_load = on_load_spy
    stages = []
    original = trainer._begin_stage
    trainer._begin_stage = lambda stage, total: (stages.append(stage), original(stage, total))
    trainer.train()
    torch.testing.assert_close(loaded["xyz"], saved["xyz"])  # loaded exactly
    assert loaded["flags"].shape == (saved["xyz"].shape[0], 1)  # the plugin's buffer was created on load
    assert stages == ["fine"]  # the coarse stage is skipped: a 4DGS output is already trained
    assert trainer.ctx.iteration == 5
    # a whole model directory works too (latest iteration)
    other = build_trainer(base_argv(tiny_scene, tmp_path / "up2", 10, 1, "--start_checkpoint", str(out)))
    other._resume_point()
    assert other.ctx.model.num_gaussians == saved["xyz"].shape[0]


def test_render_command_writes_4dgs_layout_and_metrics(trained_run):
    from baselines.fourdgs.app import render_from_argv

    out, result = trained_run
    written = render_from_argv(["-m", str(out), "--skip_train", "--skip_video"])
    method = f"ours_{result.final_iteration}"
    assert written == {"test": out / "test" / method}
    renders = sorted((out / "test" / method / "renders").glob("*.png"))
    assert len(renders) == len(list((out / "test" / method / "gt").glob("*.png"))) > 0
    assert len(list((out / "test" / method / "depth").glob("*.png"))) == len(renders)
    per_view = json.loads((out / "per_view.json").read_text())[method]
    assert set(per_view["PSNR"]) == {p.name for p in renders}
    with pytest.raises(FileNotFoundError, match="iteration_999"):
        render_from_argv(["-m", str(out), "--iteration", "999"])


def test_render_names_the_flags_that_changed_the_trained_model_shape(trained_run):
    """Shape values given to render.py (flags or --configs) that the saved files cannot fit are
    named in the load error with the trained values; a shape-neutral flag (--no_dx) still renders."""
    from baselines.fourdgs.app import render_from_argv

    out, _ = trained_run
    with pytest.raises(ValueError, match=r"given here: --net_width 16 \(trained: \d+\), --no_grid "
                                         r"\(trained: False\): a trained model's shape"):
        render_from_argv(["-m", str(out), "--skip_train", "--skip_video", "--net_width", "16", "--no_grid"])
    config = out.parent / "narrow.py"
    config.write_text("ModelHiddenParams = dict(defor_depth=3)\n")
    with pytest.raises(ValueError, match=r"deformation state does not fit.*given here: --defor_depth 3 \(trained"):
        render_from_argv(["-m", str(out), "--skip_train", "--skip_video", "--configs", str(config)])
    render_from_argv(["-m", str(out), "--skip_train", "--skip_video", "--no_dx"])


def test_non_finite_gradient_stops_the_run_naming_the_group(tiny_scene, tmp_path):
    """One NaN gradient would make Adam write NaN into the parameters: with --nonfinite_skips 0 the
    run stops before the step."""
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "nan", 3, 1, "--nonfinite_skips", "0"))
    trainer.build()
    model = trainer.ctx.model
    original = trainer.hooks.call

    def poison(name, ctx, *args):
        original(name, ctx, *args)
        if name == "post_backward" and ctx.iteration == 2:
            model._opacity.grad[0] = float("nan")

    trainer.hooks.call = poison
    before = model._opacity.detach().clone()
    with pytest.raises(FloatingPointError, match=r"iteration 2 in opacity \(lr"):
        trainer.train()
    assert torch.isfinite(model._opacity).all()  # the poisoned step never ran
    assert not torch.equal(before, model._opacity)  # iteration 1 did


def test_a_rare_non_finite_step_is_skipped_logged_and_its_state_kept(tiny_scene, tmp_path):
    """By default (--nonfinite_skips 3) one poisoned step is skipped: parameters and Adam's state
    untouched by it, the run goes on, the event and the starting state are on disk; four poisoned
    steps in a row stop the run naming the group."""
    from baselines.fourdgs.checkpoint import load_training_state

    out = tmp_path / "skip"
    trainer = build_trainer(base_argv(tiny_scene, out, 4, 1))
    trainer.build()
    model = trainer.ctx.model
    original, seen = trainer.hooks.call, {}

    def poison(name, ctx, *args):
        original(name, ctx, *args)
        if name == "post_backward" and ctx.iteration == 2:
            seen["before"] = model._opacity.detach().clone()
            seen["steps"] = int(model.optimizer.state[model._opacity]["step"])
            model._opacity.grad[0] = float("nan")
        if name == "on_iteration_end" and ctx.stage == "coarse" and ctx.iteration in (2, 4):
            seen[ctx.iteration] = (model._opacity.detach().clone(), int(model.optimizer.state[model._opacity]["step"]))

    trainer.hooks.call = poison
    trainer.train()
    assert torch.equal(seen["before"], seen[2][0]) and seen[2][1] == seen["steps"]  # the skipped step changed nothing
    assert seen[4][1] == seen["steps"] + 2  # iterations 3 and 4 stepped
    assert torch.isfinite(model._opacity).all() and trainer.nonfinite_steps == 1
    events = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    skipped = [e for e in events if e["kind"] == "nonfinite_step"]
    assert len(skipped) == 1 and skipped[0]["iteration"] == 2 and skipped[0]["groups"] == ["opacity"]
    state = load_training_state(out / "nonfinite_coarse_2.pth", trusted=True)
    assert state.iteration == 2 and torch.isnan(state.extra["grads"]["opacity"][0][0]).all()

    again = build_trainer(base_argv(tiny_scene, tmp_path / "stop", 6, 1))
    again.build()
    original_again = again.hooks.call

    def poison_always(name, ctx, *args):
        original_again(name, ctx, *args)
        if name == "post_backward" and ctx.iteration >= 2:
            again.ctx.model._opacity.grad[0] = float("nan")

    again.hooks.call = poison_always
    with pytest.raises(FloatingPointError, match=r"iteration 5 in opacity .*4 steps in a row"):
        again.train()


def test_non_finite_gradient_into_the_hexplane_is_caught_without_scanning_the_planes(tiny_scene, tmp_path):
    """The plane gradients are not scanned (too large); a NaN reaching them arrives through the
    lookup's output gradient, which also reaches feature_out's weights: the run stops there."""
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "nan_grid", 1, 3, "--nonfinite_skips", "0"))
    trainer.build()
    grid = trainer.ctx.model._deformation.deformation_net.grid

    def poison_output_gradient(module, inputs, output):
        if trainer.ctx.stage == "fine" and trainer.ctx.iteration == 2:
            output.register_hook(lambda grad: torch.full_like(grad, float("nan")))

    grid.register_forward_hook(poison_output_gradient)
    planes = [p.detach().clone() for level in grid.grids for p in level]
    with pytest.raises(FloatingPointError, match=r"fine iteration 2 in [^;]*(deformation|grid) \(lr"):
        trainer.train()
    assert all(torch.isfinite(p).all() for level in grid.grids for p in level)
    assert any(not torch.equal(a, b) for a, b in zip(planes, [p for level in grid.grids for p in level]))


def test_max_abs_flags_nan_and_inf_and_measures_finite_gradients():
    from baselines.fourdgs.trainer import _max_abs

    assert float(_max_abs([torch.tensor([1.0, -3.0]), torch.tensor([[2.0]])])) == 3.0
    assert torch.isnan(_max_abs([torch.tensor([1.0]), torch.tensor([float("nan"), 0.0])]))
    assert torch.isinf(_max_abs([torch.tensor([float("-inf")]), torch.tensor([1.0])]))


def test_adam_falls_back_where_torch_has_no_fused_kernel(monkeypatch):
    from baselines.fourdgs import gaussian_model

    real = torch.optim.Adam

    def no_fused(params, **kwargs):
        if kwargs.get("fused"):
            raise RuntimeError("`fused=True` requires all the params to be CUDA tensors")  # torch < 2.4 on CPU
        return real(params, **kwargs)

    monkeypatch.setattr(gaussian_model.torch.optim, "Adam", no_fused)
    p = torch.nn.Parameter(torch.zeros(3))
    optimizer = gaussian_model._adam([{"params": [p], "lr": 0.1, "name": "xyz"}], fused=True)
    assert not optimizer.defaults.get("fused") and optimizer.defaults["eps"] == 1e-15
    monkeypatch.setattr(gaussian_model.torch.optim, "Adam", real)
    assert gaussian_model._adam([{"params": [p], "lr": 0.1, "name": "xyz"}], fused=True).defaults["fused"]


def test_trainer_sets_the_training_time_span_and_warns_about_views_outside(tiny_scene, tmp_path, caplog):
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "span", 1, 1, "--time_outside", "hold"))
    first = min(trainer.train_cameras, key=lambda c: c.time)
    assert first.time > 0, "the tiny scene must start its training frames after t = 0"
    early = trainer.test_cameras[0]
    early.time = first.time / 2  # a held-out view before the first training frame
    with caplog.at_level("WARNING", logger="baselines.fourdgs.trainer"):
        trainer.build()
    model = trainer.ctx.model
    assert model.time_span == (first.time, max(c.time for c in trainer.train_cameras))
    assert model.time_outside == "hold"
    assert early.image_name in caplog.text and "outside the training views' time span" in caplog.text
    default = build_trainer(base_argv(tiny_scene, tmp_path / "default", 1, 1))
    default.build()
    assert default.ctx.model.time_outside == "linear"


def test_time_outside_script_rerenders_each_mode(trained_run, capsys):
    sys.path.insert(0, str(REPO_ROOT / "scripts"))
    try:
        import time_outside
    finally:
        sys.path.remove(str(REPO_ROOT / "scripts"))
    out, _ = trained_run
    row = time_outside.psnr_by_mode(out)
    assert row["outside"], "the tiny scene holds out a view before its first training frame"
    assert {m: row[m]["outside"] is not None for m in ("extrapolate", "hold", "linear")} == \
        {"extrapolate": True, "hold": True, "linear": True}
    assert row["extrapolate"]["outside"] != row["hold"]["outside"]  # the mode reached the renders
    assert time_outside.main([str(out)]) == 0
    printed = capsys.readouterr().out
    assert "extrapolate mean / outside" in printed and "mean of 1 runs" in printed


def test_lpips_values_reach_results_json_as_numbers(tiny_scene, tmp_path, monkeypatch):
    # the lpips package returns 0-dim tensors; results.json must get plain numbers (json refuses tensors)
    from baselines.fourdgs import evaluate

    monkeypatch.setattr(evaluate, "lpips_or_reason", lambda image, gt, net: (torch.tensor(0.25), None))
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "run", 0, 0))
    trainer.build()
    result = evaluate_cameras(trainer.ctx.model, trainer.test_cameras, "coarse", trainer.ctx.background, "cpu")
    evaluate.write_metrics(tmp_path / "run", "ours_0", result)
    written = json.loads((tmp_path / "run" / "results.json").read_text())["ours_0"]
    assert written["LPIPS-vgg"] == pytest.approx(0.25) and written["LPIPS-alex"] == pytest.approx(0.25)
