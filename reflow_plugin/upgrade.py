"""Upgrading a 4DGS model to ReFlow: labels from deformation magnitude, static Gaussians baked.

    python train.py -s DATA --plugin reflow --start_checkpoint OLD/point_cloud/iteration_N

A 4DGaussians output deforms every Gaussian with one HexPlane field. ReFlow's separated model
needs static/dynamic labels, so on loading such a folder (the host's `on_load` hook):

* every Gaussian is deformed to each training time t_1..t_T (the 4DGS field, all rows);
* its **motion** is the largest distance of its deformed centre from its time-averaged centre,
  max_t |mu(t) - mean_t mu(t)|;
* it is **dynamic** when that motion exceeds ``threshold`` x the scene extent (the cameras'
  radius, the quantity 4DGS scales its learning rates and densification by);
* with separation on, a static Gaussian is **baked**: its stored centre, log-scales, rotation,
  opacity logit and SH become the time averages of the deformed ones, and the separated model
  keeps it there at every time. Its centre is then within ``threshold`` x extent of where the
  4DGS model puts it at any training time, which bounds the render difference; dynamic
  Gaussians keep the 4DGS field itself (the dynamic branch has 4DGS's state-dict names) and
  render exactly as before. With separation off nothing is baked and the renders are identical;
  with `--static_decoder field` nothing is baked either: the static field starts as a copy of the
  4DGS network (`SeparatedDeformation.complete_foreign_state`), so static Gaussians move as before.

A folder written by a ReFlow run (its run's `config.json` has a ``ReFlowParams`` group) keeps
its saved labels (`deformation_table.pth`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

from arguments.saved import CONFIG_JSON


@dataclass
class MotionStatistics:
    """Per-Gaussian motion of a 4DGS model over a set of times.

    Attributes:
        motion: [N] largest distance of the deformed centre from its time average (world units).
        means, log_scales, rotations, opacity_logits: time averages of the deformed (pre-activation)
            state, [N, 3], [N, 3], [N, 4], [N, 1].
        shs: [N, K, 3] time-averaged SH coefficients.
    """

    motion: Tensor
    means: Tensor
    log_scales: Tensor
    rotations: Tensor
    opacity_logits: Tensor
    shs: Tensor


def written_by_reflow(point_cloud_dir: Path) -> bool:
    """Whether the run that wrote ``OUT/point_cloud/iteration_N`` had the ReFlow plugin loaded."""
    config = Path(point_cloud_dir).parent.parent / CONFIG_JSON
    if not config.is_file():
        return False
    try:
        return "ReFlowParams" in json.loads(config.read_text())
    except (OSError, json.JSONDecodeError):
        return False


@torch.no_grad()
def motion_statistics(model, times: Sequence[float]) -> MotionStatistics:
    """Deform every Gaussian of ``model`` (all rows, as 4DGS renders them) to each of ``times``."""
    if len(times) == 0:
        raise ValueError("motion_statistics: no times to measure the deformation at")
    saved_table = model.deformation_table
    model.set_deformation_table(torch.ones(model.num_gaussians, dtype=torch.bool))
    try:
        states = [model.deform(float(t), "fine") for t in times]
    finally:
        model.set_deformation_table(saved_table)
    means = torch.stack([s.means for s in states])                       # [T, N, 3]
    average = means.mean(0)
    motion = (means - average).norm(dim=-1).amax(0)
    return MotionStatistics(
        motion=motion, means=average,
        log_scales=torch.stack([s.log_scales for s in states]).mean(0),
        rotations=torch.stack([s.rotations for s in states]).mean(0),
        opacity_logits=torch.stack([s.opacity_logits for s in states]).mean(0),
        shs=torch.stack([s.shs for s in states]).mean(0),
    )


@torch.no_grad()
def bake_static(model, stats: MotionStatistics, static: Tensor) -> None:
    """Write the time-averaged state of the ``static`` rows ([N] bool) into the model's parameters."""
    rows = static.to(model.device)
    model._xyz[rows] = stats.means[rows]
    model._scaling[rows] = stats.log_scales[rows]
    model._rotation[rows] = stats.rotations[rows]
    model._opacity[rows] = stats.opacity_logits[rows]
    dc = model._features_dc.shape[1]
    model._features_dc[rows] = stats.shs[rows, :dc]
    model._features_rest[rows] = stats.shs[rows, dc:]


def upgrade_4dgs_model(model, times: Sequence[float], threshold: float, extent: float,
                       bake: bool) -> dict:
    """Label ``model``'s Gaussians by motion and (``bake``) freeze the static ones; returns a report.

    Args:
        model: a GaussianModel just loaded from a 4DGS folder (its deformation is 4DGS's field).
        times: the training times the motion is measured over.
        threshold: dynamic when motion > threshold x ``extent``.
        extent: the scene extent (cameras' radius), world units.
        bake: write the static rows' time averages into the parameters (separation on).
    """
    if not threshold >= 0:
        raise ValueError(f"upgrade: the motion threshold must be >= 0, got {threshold}")
    stats = motion_statistics(model, times)
    limit = threshold * extent
    dynamic = stats.motion > limit
    if bake:
        bake_static(model, stats, ~dynamic)
    model.set_deformation_table(dynamic)
    static_motion = stats.motion[~dynamic]
    return {
        "source": "4DGS checkpoint: labels from deformation magnitude",
        "times": len(times), "threshold_world": limit, "threshold_extent_fraction": threshold,
        "dynamic": int(dynamic.sum()), "static": int((~dynamic).sum()),
        "static_baked": bool(bake),
        "max_static_motion": float(static_motion.max()) if static_motion.numel() else 0.0,
        "median_motion": float(stats.motion.median()) if stats.motion.numel() else 0.0,
    }
