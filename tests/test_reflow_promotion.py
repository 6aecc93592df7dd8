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


def _view_at(cam, image: torch.Tensor, pixels: torch.Tensor):
    """A rendered batch view whose Gaussians' centres project to `pixels` [N, 2] (x, y)."""
    from baselines.fourdgs.hooks import ViewRender
    from baselines.render.projection import Projection

    n = pixels.shape[0]
    projection = Projection(means2d=pixels.float(), cov2d=torch.eye(2).expand(n, 2, 2), conics=torch.ones(n, 3),
                            depths=torch.ones(n), radii=torch.ones(n, 2, dtype=torch.int32),
                            visible=torch.ones(n, dtype=torch.bool))
    return ViewRender(camera=cam, state=None, colors=None, projection=projection, image=image)


def _missed_square(tiny_scene, tmp_path):
    """(model, a camera whose ground truth is black, a render of it that is white in one square)."""
    trainer = _built(tiny_scene, tmp_path)
    cam = trainer.train_cameras[0]
    cam = replace(cam, image=torch.zeros(cam.height, cam.width, 3))
    render_image = torch.zeros_like(cam.image)
    render_image[4:12, 4:12] = 1.0  # the model misses this square in every view
    return trainer.ctx.model, cam, render_image


def test_residual_votes_promote_static_gaussians_on_unexplained_pixels_inside_the_box(tiny_scene, tmp_path):
    from reflow_plugin.promotion import ResidualVotes

    model, cam, render_image = _missed_square(tiny_scene, tmp_path)
    n = model.num_gaussians
    q = n // 4
    pixels = torch.full((n, 2), 24.5)  # explained pixels
    pixels[:q] = 8.5  # rows 0..q: on the square (static)
    pixels[q:2 * q] = 8.5  # rows q..2q: on the square, but dynamic already
    pixels[2 * q:2 * q + 3] = -5.0  # off the image: never counted
    table = torch.zeros(n, dtype=torch.bool)
    table[q:2 * q] = True
    model.set_deformation_table(table)
    means = model.get_xyz.detach()
    model.deformation.set_aabb(means.max(0).values + 1, means.min(0).values - 1)

    votes = ResidualVotes(factor=3.0)
    view = _view_at(cam, render_image, pixels)
    for _ in range(3):
        votes.accumulate(model, view, None)
    hits, seen = (model.registered_buffers[name][:, 0] for name in (votes.HITS, votes.SEEN))
    assert torch.equal(seen[:q], torch.full((q,), 3.0)) and torch.equal(hits[:q], torch.full((q,), 3.0))
    assert not seen[q:2 * q].any()  # dynamic rows are not voted on
    assert not seen[2 * q:2 * q + 3].any()  # off the image
    assert seen[2 * q + 3:].eq(3).all() and not hits[2 * q + 3:].any()
    assert not votes.promote(model, vote=0.5, min_views=4).any()  # too few views yet
    assert not model.registered_buffers[votes.SEEN].any()  # every round starts from zero
    for _ in range(4):
        votes.accumulate(model, view, None)
    promoted = votes.promote(model, vote=0.5, min_views=4)
    assert torch.equal(promoted, torch.arange(n) < q)

    mask = torch.zeros(cam.height, cam.width, dtype=torch.bool)
    mask[2:14, 2:14] = True  # the square lies in the (estimated) mask: the dynamic branch's pixels
    for _ in range(4):
        votes.accumulate(model, view, mask)
    assert not votes.promote(model, vote=0.5, min_views=4).any()

    model.deformation.set_aabb(means.min(0).values - 1, means.min(0).values - 2)  # a box holding none
    for _ in range(4):
        votes.accumulate(model, view, None)
    assert not votes.promote(model, vote=0.5, min_views=4).any()


def test_residual_vote_counts_follow_densification(tiny_scene, tmp_path):
    from reflow_plugin.promotion import ResidualVotes

    model, cam, image = _missed_square(tiny_scene, tmp_path)
    n = model.num_gaussians
    pixels = torch.full((n, 2), 24.5)
    pixels[0] = 8.5
    model.set_deformation_table(torch.zeros(n, dtype=torch.bool))
    votes = ResidualVotes(factor=3.0)
    votes.accumulate(model, _view_at(cam, image, pixels), None)
    keep = torch.ones(n, dtype=torch.bool)
    keep[1] = False
    model.prune_points(~keep)
    hits = model.registered_buffers[votes.HITS][:, 0]
    assert hits.shape == (n - 1,) and hits[0] == 1 and not hits[1:].any()


def test_relabel_rounds_run_in_the_fine_stage_on_estimated_masks_only(tiny_scene, tmp_path):
    import json

    _reflow_run(tiny_scene, tmp_path / "est", "--label_source", "estimate", "--relabel_every", "1",
                "--densify_until_iter", "2")
    info = json.loads((tmp_path / "est" / "results.json").read_text())["reflow"]
    assert [r["iteration"] for r in info["relabel"]] == [1, 2]
    assert all(r["promoted"] >= 0 for r in info["relabel"])
    _reflow_run(tiny_scene, tmp_path / "dataset", "--relabel_every", "1", "--densify_until_iter", "2")
    assert "relabel" not in json.loads((tmp_path / "dataset" / "results.json").read_text())["reflow"]


def test_box_labels_make_every_gaussian_inside_the_dynamic_box_dynamic(tiny_scene, tmp_path):
    from types import SimpleNamespace

    from reflow_plugin.plugin import ReFlowPlugin

    trainer = _built(tiny_scene, tmp_path)
    model = trainer.ctx.model
    n = model.num_gaussians
    means = model.get_xyz.detach()
    table = torch.zeros(n, dtype=torch.bool)
    table[: n // 8] = True
    model.set_deformation_table(table)
    high, low = means[: n // 4].max(0).values, means[: n // 4].min(0).values
    model.deformation.set_aabb(high, low)
    inside = ((means >= low) & (means <= high)).all(1)
    assert 0 < int(inside.sum()) < n
    plugin = ReFlowPlugin()
    plugin._label_box(SimpleNamespace(model=model))
    assert torch.equal(model.deformation_table, table | inside)
    assert plugin.info["box_labels"] == {"before": n // 8, "dynamic": int((table | inside).sum())}
