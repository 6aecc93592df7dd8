"""Compiled flow channels (reflow_plugin/flow_kernel.py) against flow_features_torch, their torch twin.

The twin is the oracle (test_reflow_flow.py checks it against explicit matrix square roots and the
dense per-pixel flow; those tests now run through the kernel too, flow_features dispatching to it).
Covered: values and the gradients of view a's means2d and conics and view b's means2d and cov2d
on posed random pairs (float32, float64), rows that are no flow target (behind either camera,
non-finite, blown-up covariance, far off screen) and rows at the square roots' clamps (singular
and zero covariances); gradcheck in float64; thread-count independence; the fallbacks.
"""
from __future__ import annotations

import logging
from dataclasses import replace

import pytest
import torch

from baselines import native_build
from baselines.render.projection import project_gaussians_torch
from raster_cases import random_scene
from reflow_plugin import flow_kernel
from reflow_plugin.flow import flow_features, flow_features_torch


@pytest.fixture(scope="module")
def compiled():
    ok, reason = flow_kernel.LIBRARY.available()
    if not ok and native_build.find_compiler() is None:
        pytest.skip(reason)
    assert ok, reason  # a compiler is present: the kernel must build
    return ok


def _pair(n: int, dtype: torch.dtype, seed: int = 0):
    """Projections of one posed random scene into two nearby cameras (view b: moved and rescaled)."""
    s = random_scene(n, 96, 64, seed=seed, margin=0.6, pixel_sigma=(0.2, 40.0), dtype=dtype)
    view_b = s.viewmat.clone()
    view_b[:3, 3] += torch.tensor([0.3, -0.1, 0.2], dtype=dtype)
    pa = project_gaussians_torch(s.means, s.quats, s.scales, s.viewmat, s.K, 96, 64, s.opacities)
    pb = project_gaussians_torch(s.means * 1.01, s.quats, s.scales * 1.2, view_b, s.K, 96, 64, s.opacities)
    return pa, pb


def _with_hard_rows(pa, pb):
    """The pair with its first rows replaced by cases at the validity rules and the clamps."""
    pa, pb = (replace(p, **{k: p[k].detach().clone() for k in ("means2d", "cov2d", "conics", "depths")})
              for p in (pa, pb))
    pb.depths[0] = -1.0                                  # behind camera b
    pa.depths[1] = 0.005                                 # inside view a's near plane
    pb.means2d[2, 0] = float("nan")                      # non-finite in b
    pb.cov2d[3] = torch.tensor([[1.6e21, -1.5e20], [-1.5e20, 1.3e19]])  # blown up in b (trace > 1e8)
    pa.means2d[4] = torch.tensor([2e6, 10.0])            # centre beyond MAX_SCREEN_PX
    pb.cov2d[5] = torch.tensor([[4.0, 2.0], [2.0, 1.0]])  # singular: det' at its clamp
    pb.cov2d[6] = 0.0                                    # zero: the trace at its clamp too
    pa.conics[7] = torch.tensor([1.0, 1.0, 1.0])         # singular conic in a
    pa.conics[8, 1] = float("inf")                       # non-finite conic
    return pa, pb


def _channels_and_grads(fn, pa, pb, seed=0):
    leaves = [t.detach().clone().requires_grad_() for t in (pa.means2d, pa.conics, pb.means2d, pb.cov2d)]
    a = replace(pa, means2d=leaves[0], conics=leaves[1])
    b = replace(pb, means2d=leaves[2], cov2d=leaves[3])
    out = fn(a, b)
    weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=out.dtype)
    return out, torch.autograd.grad((out * weights).sum(), leaves)


def _kernel(pa, pb, threads=None):
    return flow_kernel.flow_features_kernel(pa, pb, 0.01, 1e8, 1e6, num_threads=threads)


def _float64(p):
    return replace(p, **{k: p[k].detach().double() for k in ("means2d", "cov2d", "conics", "depths")})


def _no_less_accurate(got: torch.Tensor, twin: torch.Tensor, truth: torch.Tensor, name: str) -> None:
    """float32: the kernel's largest error against the float64 truth is at most 4x the torch twin's
    (plus 1e-6 of the largest value). A float32 result of the cancelling b = t0.t1 depends on the
    compiler's and the CPU's instruction choices (fused multiply-adds), so the two float32
    computations need not agree to a fixed tolerance, only be equally close to the truth."""
    finite = torch.isfinite(truth)
    assert torch.equal(torch.isfinite(got), finite), f"{name}: non-finite entries differ from the truth's"
    err_got = (got.double() - truth)[finite].abs().max()
    err_twin = (twin.double() - truth)[finite].abs().max()
    bound = 4 * err_twin + 1e-6 * truth[finite].abs().max()
    assert err_got <= bound, f"{name}: kernel error {float(err_got):.3g} against the twin's {float(err_twin):.3g}"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("hard", [False, True], ids=["posed", "hard_rows"])
def test_kernel_equals_torch_twin(compiled, dtype, hard):
    pa, pb = _pair(3000, dtype)
    if hard:
        pa, pb = _with_hard_rows(pa, pb)
    want, want_grads = _channels_and_grads(flow_features_torch, pa, pb)
    got, got_grads = _channels_and_grads(_kernel, pa, pb)
    if hard:
        assert got[:9, 6].tolist() == [0, 0, 0, 0, 0, 1, 1, 1, 0]
    for name, g in zip(("means2d_a", "conics_a", "means2d_b", "cov2d_b"), got_grads):
        assert torch.isfinite(g).all(), name
    if dtype == torch.float32:
        truth, truth_grads = _channels_and_grads(flow_features_torch, _float64(pa), _float64(pb))
        _no_less_accurate(got, want, truth, "channels")
        for name, g, w, t in zip(("means2d_a", "conics_a", "means2d_b", "cov2d_b"), got_grads, want_grads, truth_grads):
            _no_less_accurate(g, w, t, f"{name} gradient")
        return
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-10)
    for name, g, w in zip(("means2d_a", "conics_a", "means2d_b", "cov2d_b"), got_grads, want_grads):
        scale = w.abs().max().clamp_min(1e-30)
        torch.testing.assert_close(g / scale, w / scale, rtol=1e-12, atol=1e-10,
                                   msg=lambda m, name=name: f"{name} gradient: {m}")


def test_kernel_passes_gradcheck(compiled):
    pa, pb = _pair(10, torch.float64, seed=3)
    pa.depths[0] = -1.0  # one row without a flow target
    leaves = tuple(t.detach().clone().requires_grad_() for t in (pa.means2d, pa.conics, pb.means2d, pb.cov2d))

    def channels(ma, qa, mb, sb):
        return _kernel(replace(pa, means2d=ma, conics=qa), replace(pb, means2d=mb, cov2d=sb))

    assert torch.autograd.gradcheck(channels, leaves, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_results_do_not_depend_on_the_thread_count(compiled):
    pa, pb = _pair(9000, torch.float32, seed=4)  # several blocks of 4096 rows
    (o1, g1), (o3, g3) = (_channels_and_grads(lambda a, b, t=t: _kernel(a, b, t), pa, pb) for t in (1, 3))
    assert torch.equal(o1, o3)
    assert all(torch.equal(a, b) for a, b in zip(g1, g3))


def test_flow_features_dispatch_and_fallbacks(compiled, monkeypatch, caplog):
    pa, pb = _pair(50, torch.float32, seed=5)
    pa = replace(pa, means2d=pa.means2d.detach().requires_grad_())
    assert type(flow_features(pa, pb).grad_fn).__name__ == "_FlowKernelBackward"
    monkeypatch.setattr(flow_kernel, "_logged_reasons", set())
    with caplog.at_level(logging.INFO, logger=flow_kernel.__name__):
        for name in (flow_kernel.ENV_SWITCH, flow_kernel.ENV_ALL_KERNELS):
            monkeypatch.setenv(name, "off")
            assert type(flow_features(pa, pb).grad_fn).__name__ != "_FlowKernelBackward"
            monkeypatch.delenv(name)
        # projections of mixed dtypes take the torch version
        mixed = replace(pb, means2d=pb.means2d.double())
        assert flow_kernel.unusable_reason(pa, mixed) is not None
    assert len([r for r in caplog.records if r.name == flow_kernel.__name__]) == 2


def test_missing_compiler_falls_back_to_the_torch_twin(monkeypatch, tmp_path, caplog):
    monkeypatch.setenv(native_build.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.setenv("CXX", "no-such-compiler-reflow4dgs")
    monkeypatch.setattr(flow_kernel, "_logged_reasons", set())
    flow_kernel.LIBRARY.reset()
    try:
        pa, pb = _pair(20, torch.float32, seed=6)
        with caplog.at_level(logging.INFO, logger=flow_kernel.__name__):
            got = flow_features(pa, pb)
        assert torch.equal(got, flow_features_torch(pa, pb))
        records = [r for r in caplog.records if r.name == flow_kernel.__name__]
        assert len(records) == 1 and records[0].levelno == logging.WARNING
        assert "no C++ compiler" in records[0].getMessage()
    finally:
        flow_kernel.LIBRARY.reset()
