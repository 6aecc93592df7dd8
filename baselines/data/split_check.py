"""Warn when the test split repeats training views: test metrics would then not measure novel views.

Seen: a converted NVIDIA folder read by the D-NeRF reader whose ``transforms_test.json`` listed
the training frames. A test view repeats a training view when both have the same image name, or
the same time and the same pose (world->camera matrices equal to ``tol``).
"""
from __future__ import annotations

import logging

import torch

from .scene_info import SceneInfo

log = logging.getLogger(__name__)


def overlapping_test_views(scene: SceneInfo, tol: float = 1e-6) -> list[int]:
    """Indices of the test cameras that repeat a training camera (see the module docstring)."""
    names = {c.image_name for c in scene.train_cameras}
    by_time: dict[float, list[torch.Tensor]] = {}
    for camera in scene.train_cameras:
        by_time.setdefault(round(float(camera.time), 9), []).append(camera.viewmat.detach().cpu())
    repeated = []
    for k, camera in enumerate(scene.test_cameras):
        viewmat = camera.viewmat.detach().cpu()
        same_pose = any(torch.allclose(viewmat, other, atol=tol, rtol=0.0)
                        for other in by_time.get(round(float(camera.time), 9), []))
        if camera.image_name in names or same_pose:
            repeated.append(k)
    return repeated


def warn_split_overlap(scene: SceneInfo) -> list[int]:
    """Log one warning when test views repeat training views; returns their indices."""
    repeated = overlapping_test_views(scene)
    if repeated:
        which = "identical to" if len(repeated) == len(scene.test_cameras) else "overlapping"
        log.warning("%s: the test split is %s the training split (%d of %d test views are training views: "
                    "same image or same pose and time); test metrics will not measure novel views",
                    scene.source_path, which, len(repeated), len(scene.test_cameras))
    scene.metadata["test_views_in_train"] = len(repeated)
    return repeated
