"""The final-stretch rule: no opacity reset / densification right before a saved or final iteration."""
from __future__ import annotations

import json

import torch

from baselines.fourdgs.app import REPO_ROOT, build_trainer
from baselines.fourdgs.densification import densification_step
from baselines.fourdgs.final_stretch import RESET_RECOVERY_ITERATIONS, FinalStretch, final_stretch
from tests._model_helpers import make_model, opt_args


def test_rule_window_and_kept_iterations():
    opt = opt_args(opacity_reset_interval=3000)
    # lego at --iterations 3000: the reset due at the final iteration is forbidden, and so is any
    # reset in the last 500 iterations; densification only at the kept iteration itself.
    assert final_stretch(opt, 3000, "fine", 3000, []) == FinalStretch(allow_reset=False, allow_densify=False)
    assert not final_stretch(opt, 3000 - RESET_RECOVERY_ITERATIONS + 1, "fine", 3000, []).allow_reset
    assert final_stretch(opt, 3000 - RESET_RECOVERY_ITERATIONS, "fine", 3000, []) == FinalStretch()
    assert final_stretch(opt, 2999, "fine", 3000, []).allow_densify
    # a saved iteration the user asks for is kept too; save iterations beyond the stage are ignored
    assert final_stretch(opt, 1200, "fine", 3000, [1200, 9000]) == FinalStretch(False, False)
    assert final_stretch(opt, 1300, "fine", 3000, [1200, 9000]) == FinalStretch()
    # the window never exceeds the reset interval; the coarse stage is never restricted
    small = opt_args(opacity_reset_interval=10)
    assert final_stretch(small, 30, "fine", 40, []).allow_reset
    assert not final_stretch(small, 31, "fine", 40, []).allow_reset
    assert final_stretch(opt, 3000, "coarse", 3000, []) == FinalStretch()


def test_densification_step_skips_and_records():
    opt = opt_args(densify_from_iter=2, densification_interval=5, pruning_from_iter=2, pruning_interval=5,
                   opacity_reset_interval=5, densify_until_iter=20)
    model = make_model(count=30)
    before = model.get_opacity.detach().clone()
    record = densification_step(
        model, opt, 10, "fine", cameras_extent=100.0, visible=torch.ones(30, dtype=torch.bool),
        radii=torch.zeros(30), means2d_grad=torch.zeros(30, 2), width=64, height=48, prune_min_gaussians=0,
        stretch=FinalStretch(allow_reset=False, allow_densify=False),
    )
    assert record.skipped == ["densify", "prune", "opacity_reset"]
    assert not (record.densify_ran or record.prune_ran or record.opacity_reset)
    torch.testing.assert_close(model.get_opacity.detach(), before)


def test_final_iteration_reset_does_not_collapse_model(tiny_scene, tmp_path):
    # Fine stage of 30 iterations whose last one is both a reset and a densification iteration.
    argv = ["-s", str(tiny_scene), "-m", str(tmp_path / "run"),
            "--configs", str(REPO_ROOT / "arguments/synthetic/default.py"), "--quiet",
            "--coarse_iterations", "10", "--iterations", "30", "--test_iterations", "[20]", "--save_iterations", "[]",
            "--opacity_reset_interval", "30", "--densify_from_iter", "5", "--densification_interval", "15",
            "--densify_until_iter", "100", "--pruning_from_iter", "5", "--pruning_interval", "15",
            "--prune_min_gaussians", "0"]
    trainer = build_trainer(argv)
    trainer.train()
    opacity = trainer.ctx.model.get_opacity.detach()
    assert opacity.max() > 0.05, "the final iteration reset the opacities"
    events = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    skips = [e for e in events if e["kind"] == "final_stretch"]
    assert [(e["stage"], e["iteration"], e["skipped"]) for e in skips] == [
        ("fine", 30, ["densify", "prune", "opacity_reset"])]
    tests = {e["iteration"]: e["test_psnr"] for e in events if e["kind"] == "test" and e["stage"] == "fine"}
    assert tests[30] >= tests[20] - 0.5, tests  # a reset at 30 would drop it by several dB
    densified = [e for e in events if e["kind"] == "saved"]
    assert densified, "the final model is saved"


def test_synthetic_default_schedule_is_untouched():
    from arguments import parse_train_args

    args = parse_train_args(["--configs", str(REPO_ROOT / "arguments/synthetic/default.py")])
    opt, run = args.opt, args.run
    # densification stops at densify_until_iter < every kept iteration and no reset ever fires
    for iteration in range(1, opt.iterations + 1):
        stretch = final_stretch(opt, iteration, "fine", opt.iterations, run.save_iterations)
        if stretch.restricted:
            assert iteration >= opt.densify_until_iter and iteration % opt.opacity_reset_interval != 0
