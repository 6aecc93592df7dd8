"""The flow provider's partner spread (REFLOW4DGS_FLOW_SPREAD, `FlowProvider.fused_depth`) and its
DIS pyramid's finest level (REFLOW4DGS_FLOW_FINEST).

A camera sliding 1 cm per frame past a slanted wall 5 m away: neighbouring frames see 0.2 px of
parallax, so 0.05 px of flow noise is 25% of depth. The flows are exact plus seeded noise
(injected into the provider's flow cache: DIS itself is not under test here).
"""
from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from reflow_plugin.canonical import options_from_params
from reflow_plugin.canonical.providers import FlowProvider
from reflow_plugin.params import FLOW_FINEST_SWITCH, FLOW_SPREAD_SWITCH, ReFlowParams, flow_spread_from_env

W, H, FOCAL, FRAMES, STEP, NOISE_PX = 64, 48, 100.0, 12, 0.01, 0.05


def _camera(n: int) -> SimpleNamespace:
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[0, 3] = -STEP * n  # centre (STEP n, 0, 0), looking along +z
    K = torch.tensor([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1]], dtype=torch.float64)
    return SimpleNamespace(K=K, viewmat=viewmat, time=n / FRAMES, frame_index=n, width=W, height=H,
                           image=torch.zeros(H, W, 3))


def _true_depth(n: int) -> np.ndarray:
    """[H, W] z-depth of frame n on the wall Z = 5 + 0.2 X."""
    xs = (np.arange(W) + 0.5 - W / 2) / FOCAL
    return np.broadcast_to((5.0 + 0.2 * STEP * n) / (1.0 - 0.2 * xs)[None, :], (H, W))


def _exact_flow(i: int, j: int) -> np.ndarray:
    """[H, W, 2] flow i -> j of the wall (cameras differ by a translation along x only)."""
    z = _true_depth(i)
    flow = np.zeros((H, W, 2), np.float32)
    flow[..., 0] = -FOCAL * STEP * (j - i) / z
    return flow


def _provider(spread: int, seed: int = 0) -> FlowProvider:
    provider = FlowProvider([_camera(n) for n in range(FRAMES)], stride=1, spread=spread)
    rng = np.random.default_rng(seed)
    for i in range(FRAMES):
        for j in range(FRAMES):
            if i != j:
                noise = rng.normal(0.0, NOISE_PX, (H, W, 2)).astype(np.float32)
                provider._flows[(i, j)] = _exact_flow(i, j) + noise
    return provider


def _median_error(provider: FlowProvider, frames: range) -> float:
    errors = []
    for n in frames:
        depth, conf = provider.depth(n, full=True)
        assert np.isfinite(depth).all() and np.isfinite(conf).all() and (conf >= 0).all()
        errors.append(np.abs(depth / _true_depth(n) - 1)[conf > 0])
    return float(np.median(np.concatenate(errors)))


def test_a_sequence_with_little_parallax_is_triangulated_better_with_farther_partners():
    near, wide = _provider(1), _provider(4)
    assert not near.rig and not near.fused and wide.fused
    assert near.partners(5) == [4, 6] and wide.partners(1) == [0, 2, 3, 4, 5]
    frames = range(2, FRAMES - 2)
    error_near, error_wide = _median_error(near, frames), _median_error(wide, frames)
    assert error_near > 0.08  # 0.2 px of parallax against 0.05 px of noise (x sqrt 2 for fb)
    assert error_wide < 0.4 * error_near, (error_near, error_wide)
    assert near.key() != wide.key()  # the canonical cache tells them apart


def test_fused_depth_ignores_a_partner_whose_flow_failed():
    clean, broken = _provider(3), _provider(3)
    broken._flows[(5, 8)] = _exact_flow(5, 8) * 3.0  # one partner's flow three times too long, fb-consistent
    broken._flows[(8, 5)] = _exact_flow(8, 5) * 3.0
    depth_clean, _ = clean.depth(5, full=True)
    depth_broken, _ = broken.depth(5, full=True)
    assert np.median(np.abs(depth_broken / depth_clean - 1)) < 0.05  # the weighted median outvotes it


def test_switches_are_read_and_a_bad_value_is_one_error(monkeypatch):
    monkeypatch.delenv(FLOW_SPREAD_SWITCH, raising=False)
    monkeypatch.delenv(FLOW_FINEST_SWITCH, raising=False)
    options = options_from_params(ReFlowParams())
    assert flow_spread_from_env() == 1 and options.flow_spread == 1 and options.flow_finest_scale is None
    monkeypatch.setenv(FLOW_SPREAD_SWITCH, "4")
    monkeypatch.setenv(FLOW_FINEST_SWITCH, "0")
    options = options_from_params(ReFlowParams())
    assert options.flow_spread == 4 and options.flow_finest_scale == 0
    from reflow_plugin.plugin import ReFlowPlugin

    for name, bad in ((FLOW_SPREAD_SWITCH, "0"), (FLOW_SPREAD_SWITCH, "two"), (FLOW_SPREAD_SWITCH, "-3"),
                      (FLOW_FINEST_SWITCH, "-1"), (FLOW_FINEST_SWITCH, "full")):
        monkeypatch.setenv(FLOW_SPREAD_SWITCH, "4")
        monkeypatch.setenv(FLOW_FINEST_SWITCH, "0")
        monkeypatch.setenv(name, bad)
        with pytest.raises(ValueError, match=name):
            ReFlowPlugin()  # refused when the plugin is made, before any data is read
    with pytest.raises(ValueError, match="spread"):
        FlowProvider([_camera(0), _camera(1)], spread=0)


def test_finest_level_reaches_dis_and_the_cache_key():
    preset, full = FlowProvider([_camera(n) for n in range(3)]), FlowProvider([_camera(n) for n in range(3)],
                                                                             finest_scale=0)
    assert preset._dis.getFinestScale() == 1 and full._dis.getFinestScale() == 0
    assert preset.key() != full.key() and "finest=0" in full.key()
    # a textured image shifted by 0.6 px: the full-resolution flow measures it closer than the preset's
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (H * 2, W * 2)).astype(np.float32), (0, 0), 1.5)
    first = cv2.resize(texture, (W, H), interpolation=cv2.INTER_AREA)
    shift = np.float32([[1, 0, 0.6], [0, 1, 0]])
    second = cv2.warpAffine(first, shift, (W, H), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    first, second = (np.clip(im, 0, 255).astype(np.uint8) for im in (first, second))
    inner = (slice(8, H - 8), slice(8, W - 8))
    errors = [np.median(np.abs(p._dis.calc(first, second, None)[inner][..., 0] - 0.6)) for p in (preset, full)]
    assert errors[1] < errors[0], errors


def test_canonical_flow_benchmark_skips_what_it_cannot_measure_and_prints_its_rows(tiny_scene):
    from baselines.data import load_scene
    from benchmarks import canonical_flow

    scene = load_scene(tiny_scene, eval=True)  # the simulator writes disparity: the depth provider's case
    assert canonical_flow.usable(scene) == "has disparity: ReFlow uses the depth provider"
    text = canonical_flow.table([
        {"capture": "a", "skipped": "why"},
        {"capture": "b", "spread": 4, "finest": 0, "align": False, "static": 1234, "seconds": 2.0, "error": 0.018,
         "ratio": [0.9, 1.0, 1.1]},
        {"capture": "c", "spread": 1, "finest": "preset", "align": True, "static": 0, "seconds": 1.0}])
    assert "| a | - | - | - | skipped: why |" in text
    assert "| b | 4 | 0 | off | 1.8 | 0.900 / 1.000 / 1.100 | 1,234 | 2 |" in text
    assert "| c | 1 | preset | on | no cell | - | 0 | 1 |" in text
