"""Continuing from an old output folder: its saved model hyperparameters, or a hint naming the config."""
from __future__ import annotations

import argparse

import pytest

from baselines.fourdgs.app import REPO_ROOT, build_trainer

SYNTHETIC = str(REPO_ROOT / "arguments/synthetic/default.py")
SHORT = ["--quiet", "--test_iterations", "[]", "--save_iterations", "[]", "--densify_until_iter", "0"]


def _old_4dgs_output(tiny_scene, root):
    """A finished run whose cfg_args is 4DGS-style (flat Namespace, configs as one string)."""
    old = root / "old"
    build_trainer(["-s", str(tiny_scene), "-m", str(old), "--configs", SYNTHETIC, "--net_width", "32",
                   "--coarse_iterations", "2", "--iterations", "2", *SHORT]).train()
    flat = vars(eval((old / "cfg_args").read_text(), {"Namespace": argparse.Namespace}))  # noqa: S307
    flat["configs"] = "arguments/dnerf/lego.py"
    (old / "cfg_args").write_text(repr(argparse.Namespace(**flat)))
    (old / "config.json").unlink()  # 4DGS writes cfg_args only
    return old


def test_start_from_old_folder_reads_its_model_config_or_names_the_config(tiny_scene, tmp_path):
    old = _old_4dgs_output(tiny_scene, tmp_path)
    start = ["--start_checkpoint", str(old / "point_cloud" / "iteration_2")]
    run = ["-s", str(tiny_scene), "--coarse_iterations", "0", "--iterations", "2", *SHORT, *start]
    trainer = build_trainer([*run, "-m", str(tmp_path / "new")])
    assert trainer.hidden.net_width == 32  # from the old cfg_args, no --configs given
    assert trainer.args.sources["ModelHiddenParams.net_width"].endswith("cfg_args")
    # the schedule is the family's config (as without --start_checkpoint), not 4DGS's bare defaults
    assert trainer.opt.prune_min_gaussians == 0 and trainer.opt.opacity_reset_interval == 100_000
    assert trainer.args.sources["OptimizationParams.prune_min_gaussians"].endswith("synthetic/default.py")
    # the old run's time cells are kept (its grid's shape), not refitted to this capture's frames
    assert trainer.hidden.kplanes_config["resolution"] == [32, 32, 32, 12]
    trainer.train()
    assert trainer.ctx.model.num_gaussians > 0

    # An explicit --configs wins; shapes then disagree and the error names the config to pass.
    mismatched = build_trainer([*run, "-m", str(tmp_path / "bad"), "--configs", SYNTHETIC])
    assert mismatched.hidden.net_width == 64
    with pytest.raises(ValueError, match=r"deformation\.pth.*--configs arguments/dnerf/lego\.py"):
        mismatched.train()


def test_resume_from_a_4dgs_chkpnt_with_numpy_scalars(tiny_scene, tmp_path):
    import numpy as np
    import torch

    run = ["-s", str(tiny_scene), "--configs", SYNTHETIC, "--coarse_iterations", "2", *SHORT]
    first = build_trainer([*run, "-m", str(tmp_path / "a"), "--iterations", "2", "--checkpoint_iterations", "2"])
    first.train()
    ours = torch.load(tmp_path / "a" / "chkpnt_fine_2.pth", weights_only=False)
    capture = list(ours["capture"][:14])  # 4DGS: (gaussians.capture(), iteration), numpy lrs inside
    for group in capture[12]["param_groups"]:
        group["lr"] = np.float64(group["lr"])
    capture[13] = np.float64(capture[13])
    four_dgs = tmp_path / "old" / "chkpnt_fine_2.pth"
    four_dgs.parent.mkdir()
    torch.save((tuple(capture), 2), four_dgs)
    resumed = build_trainer([*run, "-m", str(tmp_path / "b"), "--iterations", "4", "--start_checkpoint", str(four_dgs)])
    result = resumed.train()
    assert result.final_iteration == 4 and resumed.ctx.model.num_gaussians == first.ctx.model.num_gaussians


def test_a_dataset_named_in_a_config_file_is_trained_not_the_embedded_scene(tiny_scene, tmp_path):
    from baselines.fourdgs.app import resolve_train_args

    config = tmp_path / "cfg.py"
    config.write_text(f"ModelParams = dict(source_path={str(tiny_scene)!r})\n")
    resolved = resolve_train_args(["--configs", SYNTHETIC, str(config), "-m", str(tmp_path / "run")])
    assert not resolved.embedded and resolved.source == tiny_scene
    assert resolve_train_args(["--configs", SYNTHETIC, "-m", str(tmp_path / "run")]).embedded
