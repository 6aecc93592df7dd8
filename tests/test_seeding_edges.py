"""Keyframe seeds on a monocular depth map's soft edges (reflow_plugin/seeding.py)."""
from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import torch

from reflow_plugin.seeding import depth_edges, seed_dynamic_points, snap_edges_to_nearer


def _box_in_front(blur: float) -> tuple[np.ndarray, np.ndarray]:
    """(depth [40, 40]: a box at 300 in front of a wall at 450, edges blurred; the box's mask)."""
    depth = np.full((40, 40), 450.0)
    depth[10:30, 10:30] = 300.0
    mask = depth < 400
    return (cv2.GaussianBlur(depth, (0, 0), blur) if blur else depth), mask


def test_depth_edges_mark_the_rims_and_nothing_flat():
    depth, mask = _box_in_front(0.0)
    edges = depth_edges(depth, 1.1)
    assert edges[10, 15] and edges[9, 15] and not edges[20, 20] and not edges[2, 2]
    slanted = np.tile(np.linspace(100.0, 110.0, 40), (40, 1))  # 0.25% per pixel: no edge
    assert not depth_edges(slanted, 1.1).any()
    holes = depth.copy()
    holes[20, 20] = np.nan
    assert depth_edges(holes, 1.1)[20, 20] and depth_edges(holes, 1.1)[19, 19]  # no depth: an edge


def test_soft_rims_are_snapped_to_the_nearer_surface():
    soft, mask = _box_in_front(1.5)
    error = np.abs(soft[mask] / 300.0 - 1.0)
    snapped = snap_edges_to_nearer(soft, 1.1)
    fixed = np.abs(snapped[mask] / 300.0 - 1.0)
    assert np.percentile(error, 90) > 0.15 and np.percentile(fixed, 90) < 0.05
    assert np.array_equal(snapped[~depth_edges(soft, 1.1)], soft[~depth_edges(soft, 1.1)])  # elsewhere unchanged


def test_seeds_from_a_soft_depth_map_sit_on_the_object_with_the_edge_ratio():
    soft, mask = _box_in_front(1.5)
    K = torch.tensor([[40.0, 0.0, 20.0], [0.0, 40.0, 20.0], [0.0, 0.0, 1.0]])
    camera = SimpleNamespace(K=K, viewmat=torch.eye(4), image=torch.rand(40, 40, 3))
    plain = seed_dynamic_points(camera, mask, soft, 10_000)
    snapped = seed_dynamic_points(camera, mask, soft, 10_000, edge_ratio=1.1)
    assert len(plain) == len(snapped) == int(mask.sum())  # every masked pixel keeps its seed
    assert np.percentile(np.abs(plain.points[:, 2] / 300 - 1), 90) > 0.15
    assert np.percentile(np.abs(snapped.points[:, 2] / 300 - 1), 90) < 0.05
    flat = seed_dynamic_points(camera, mask, 300.0, 10_000, edge_ratio=1.1)  # one depth: nothing to snap
    np.testing.assert_allclose(flat.points[:, 2], 300.0, rtol=1e-6)


def test_an_edge_ratio_of_at_most_one_is_a_flag_error(capsys):
    """--seed_edge_ratio 0.5 passed the >= 0 check, and at a ratio <= 1 every pixel whose neighbourhood is
    not flat is an "edge": every seed took the nearest depth of its 5x5 neighbourhood."""
    import pytest

    from arguments import parse_train_args
    from reflow_plugin.params import ReFlowParams

    depth, _ = _box_in_front(2.0)
    assert depth_edges(depth, 0.5).all()
    for value in ("0.5", "1"):
        with pytest.raises(SystemExit):
            parse_train_args(["--seed_edge_ratio", value], extra_groups={"ReFlowParams": ReFlowParams})
        assert f"argument --seed_edge_ratio: must be 0 (off) or > 1, got {float(value)}" in capsys.readouterr().err
    for value in ("0", "1.05"):
        args = parse_train_args(["--seed_edge_ratio", value], extra_groups={"ReFlowParams": ReFlowParams})
        assert args.extra["ReFlowParams"].seed_edge_ratio == float(value)
