"""Multi-camera rigs read monocularly: which training frames share one rig camera, and whether
consecutive frames jump between distant ones.

    groups = pose_groups(viewmats)      # [N] int, equal for frames with the same camera pose
    wide = wide_rig(viewmats)           # viewmats in time order: a camera pose recurs AND
                                        # consecutive frames' viewing directions differ by at least
                                        # WIDE_ANGLE_DEG (median)

NVIDIA's monocular protocol and panoptic's camera cycle build a "video" by taking frame t from
rig camera t mod C. When the cycle's cameras are far apart (CMU Panoptic basketball: five dome
cameras 26-68 degrees apart, median 34 between consecutive frames) "close in time" no longer
means "close in viewpoint": optical flow between time neighbours is a wide-baseline match that
DIS does not find from zero. The plugin then pairs frames by camera instead of by time: the
canonical space's flow provider triangulates each frame with the nearest OTHER rig cameras
(canonical/providers.py) and motion masks are estimated along each camera's own frames
(labels.py), where the static scene does not move at all. A narrow rig (the simulator's 12-camera
rigs: a few degrees between neighbours) and a video (every pose new) keep time order, which is
their viewpoint order.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

SAME_POSE = 1e-6  # two viewmats closer than this (largest absolute entry difference) are one rig camera
WIDE_ANGLE_DEG = 10.0  # median angle between consecutive frames' viewing directions from which a rig is "wide"


def pose_groups(viewmats: Sequence[np.ndarray]) -> np.ndarray:
    """[N] int: frames with the same camera pose (viewmats [4, 4] within SAME_POSE) share a group
    id; ids are 0, 1, ... in order of first appearance."""
    mats = np.asarray([np.asarray(v, np.float64) for v in viewmats]).reshape(len(viewmats), -1)
    groups = np.full(len(mats), -1)
    for n in range(len(mats)):
        if groups[n] < 0:
            same = (groups < 0) & (np.abs(mats - mats[n]).max(axis=1) <= SAME_POSE)
            groups[same] = groups.max() + 1
    return groups


def viewing_angle_deg(viewmat_a: np.ndarray, viewmat_b: np.ndarray) -> float:
    """Angle in degrees between two cameras' viewing directions (their optical axes)."""
    axis_a, axis_b = np.asarray(viewmat_a, np.float64)[2, :3], np.asarray(viewmat_b, np.float64)[2, :3]
    return float(np.degrees(np.arccos(np.clip(axis_a @ axis_b, -1.0, 1.0))))


def wide_rig(viewmats: Sequence[np.ndarray]) -> bool:
    """Whether frames (viewmats in TIME order) come from a rig read monocularly whose consecutive
    frames are far apart: some pose recurs and the median angle between consecutive frames'
    viewing directions is at least WIDE_ANGLE_DEG."""
    if len(viewmats) < 2 or int(pose_groups(viewmats).max()) + 1 == len(viewmats):
        return False
    angles = [viewing_angle_deg(a, b) for a, b in zip(viewmats[:-1], viewmats[1:])]
    return float(np.median(angles)) >= WIDE_ANGLE_DEG
