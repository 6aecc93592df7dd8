"""Promotion of static Gaussians where the coarse fit leaves unmasked pixels unexplained."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from baselines.fourdgs.app import build_trainer
from baselines.fourdgs.renderer import render
from reflow_plugin.promotion import missed_motion_maps, promoted_gaussians
from tests.test_trainer import base_argv


def _built(tiny_scene, tmp_path):
    trainer = build_trainer(base_argv(tiny_scene, tmp_path / "run", 0, 0))
    trainer.build()
    return trainer


def test_flags_unexplained_unmasked_pixels_only(tiny_scene, tmp_path):
    trainer = _built(tiny_scene, tmp_path)
    model, background = trainer.ctx.model, trainer.ctx.background
    cameras = []
    for cam in trainer.train_cameras[:3]:  # ground truth = the model's own render, then a square changed
        image = render(model, cam, "coarse", background, "cpu").image.clamp(0, 1).detach().clone()
        image[4:12, 4:12] = 1.0 - image[4:12, 4:12]
        image[20:28, 20:28] = 1.0 - image[20:28, 20:28]
        cameras.append(replace(cam, image=image))
    masks = [np.zeros((32, 32), bool) for _ in cameras]
    for mask in masks:
        mask[18:30, 18:30] = True  # the second square is inside the (estimated) mask
    flagged = missed_motion_maps(model, cameras, masks, background, factor=4.0, backend="cpu")
    for hit in flagged:
        assert hit[4:12, 4:12].mean() > 0.5  # the unexplained square outside the mask
        assert not hit[18:30, 18:30].any()  # masked pixels are the dynamic branch's already
        outside = hit.copy()
        outside[3:13, 3:13] = False
        assert not outside.any()  # nothing else: the render explains it


def test_only_static_gaussians_seen_in_flagged_pixels_are_promoted(tiny_scene, tmp_path):
    trainer = _built(tiny_scene, tmp_path)
    model, cameras = trainer.ctx.model, trainer.train_cameras
    n = model.num_gaussians
    table = torch.zeros(n, dtype=torch.bool)
    table[: n // 4] = True
    model.set_deformation_table(table)
    everywhere = [np.ones((c.height, c.width), bool) for c in cameras]
    promoted = promoted_gaussians(model, cameras, everywhere, vote=0.5)
    assert promoted.shape == (n,) and not promoted[: n // 4].any()  # already dynamic: untouched
    assert promoted[n // 4:].sum() > 0
    nowhere = [np.zeros((c.height, c.width), bool) for c in cameras]
    assert not promoted_gaussians(model, cameras, nowhere, vote=0.5).any()


def _reflow_run(tiny_scene, out, *extra, coarse: int = 20):
    from tests.test_reflow_plugin import _argv

    trainer = build_trainer(_argv(tiny_scene, out, coarse, 2, *extra))
    trainer.build()
    trainer.train()


def test_promotion_runs_once_at_the_fine_start_on_estimated_masks_only(tiny_scene, tmp_path):
    import json

    _reflow_run(tiny_scene, tmp_path / "est", "--label_source", "estimate", "--promote_residual", "3")
    info = json.loads((tmp_path / "est" / "results.json").read_text())["reflow"]
    assert info["mask_source"] == "estimated"
    promotion = info["promotion"]
    assert promotion["dynamic"] >= promotion["promoted"] >= 0
    assert 0.0 <= promotion["flagged_pixel_share"] < 1.0
    _reflow_run(tiny_scene, tmp_path / "dataset", "--promote_residual", "3")  # the dataset's masks: trusted
    info = json.loads((tmp_path / "dataset" / "results.json").read_text())["reflow"]
    assert info["mask_source"] != "estimated" and "promotion" not in info
    _reflow_run(tiny_scene, tmp_path / "no_coarse", "--label_source", "estimate", "--promote_residual", "3", coarse=0)
    assert "promotion" not in json.loads((tmp_path / "no_coarse" / "results.json").read_text())["reflow"]
