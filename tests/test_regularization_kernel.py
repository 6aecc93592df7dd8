"""Compiled HexPlane regularisers (baselines/fourdgs/regularization_kernel.py) against the torch Function.

The torch Function (regularization._WeightedPlaneRegularisation) and the formula-level reference
(hexplane_regularization_reference) are the oracles; test_hexplane.py's regulariser tests run
through the kernel too (it is the default on CPU). Covered: value and gradients in float64
(tight) and float32 on HexPlane planes that are views of one channels-last table and on plain,
permuted and expanded planes, planes too short for a second difference, zero weights, planes at
exactly 1 (the L1 kink), gradcheck, a scaled incoming gradient, accumulation into existing
gradients and a retained graph's second backward, bitwise thread-count independence, and the
fallbacks (environment switches, no compiler, other dtypes).
"""
from __future__ import annotations

import logging

import pytest
import torch

from baselines import native_build
from baselines.fourdgs import regularization_kernel
from baselines.fourdgs.hexplane import HexPlaneField
from baselines.fourdgs.plane_lookup import shared_table
from baselines.fourdgs.regularization import (
    TIME_PLANES,
    _WeightedPlaneRegularisation,
    hexplane_regularization,
    hexplane_regularization_reference,
)

CONFIG = {"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 5, "resolution": [6, 7, 9, 8]}
WEIGHTS = (0.01, 0.001, 0.1)  # time smoothness, L1 of the time planes, plane TV (4DGS's argument order)


@pytest.fixture(scope="module")
def compiled():
    ok, reason = regularization_kernel.LIBRARY.available()
    if not ok and native_build.find_compiler() is None:
        pytest.skip(reason)
    assert ok, reason  # a compiler is present: the kernel must build
    return ok


def _field(dtype: torch.dtype, resolution=None, seed: int = 0) -> HexPlaneField:
    """A two-level field with random planes (some values exactly 1), packed into one shared table."""
    torch.manual_seed(seed)
    field = HexPlaneField(1.0, {**CONFIG, "resolution": resolution or CONFIG["resolution"]}, [1, 2]).to(dtype)
    with torch.no_grad():
        for level in field.grids:
            for plane in level:
                plane.add_(torch.randn_like(plane))
                plane.masked_fill_(torch.rand_like(plane) < 0.1, 1.0)  # |1 - p| at its kink
    field.pack_planes()
    return field


def _planes(field: HexPlaneField) -> list[torch.Tensor]:
    return [p for level in field.grids for p in level]


def _flat_weights(levels, weights) -> tuple[list[float], list[float]]:
    """The per-plane (smooth, l1) weights hexplane_regularization gives 6-plane levels."""
    time_smooth, l1_time, plane_tv = weights
    smooth, l1 = [], []
    for level in levels:
        for index in range(len(level)):
            smooth.append(time_smooth if index in TIME_PLANES else plane_tv)
            l1.append(l1_time if index in TIME_PLANES else 0.0)
    return smooth, l1


def _torch_function(levels, *weights):
    smooth, l1 = _flat_weights(levels, weights)
    return _WeightedPlaneRegularisation.apply(tuple(smooth), tuple(l1), *[p for level in levels for p in level])


def _value_and_grads(fn, levels, weights):
    planes = [p for level in levels for p in level]
    value = fn(levels, *weights)
    grads = torch.autograd.grad(value, planes, allow_unused=True)
    return value.detach(), [torch.zeros_like(p) if g is None else g for g, p in zip(grads, planes)]


def _kernel_value_and_grads(monkeypatch, levels, weights):
    monkeypatch.setenv(regularization_kernel.ENV_SWITCH, "1")
    value = hexplane_regularization(levels, *weights)
    assert type(value.grad_fn).__name__ == "_KernelRegularisationBackward"
    planes = [p for level in levels for p in level]
    grads = torch.autograd.grad(value, planes, allow_unused=True)
    return value.detach(), [torch.zeros_like(p) if g is None else g for g, p in zip(grads, planes)]


def _tolerance(dtype):
    return {"rtol": 1e-5, "atol": 1e-7} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-15}


def _assert_matches(got, want, dtype):
    (value, grads), (want_value, want_grads) = got, want
    torch.testing.assert_close(value, want_value, **_tolerance(dtype))
    for k, (g, w) in enumerate(zip(grads, want_grads)):
        scale = w.abs().max().clamp_min(1e-30)
        torch.testing.assert_close(g / scale, w / scale, **_tolerance(dtype), msg=lambda m, k=k: f"plane {k}: {m}")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("weights", [WEIGHTS, (0.0, 0.3, 0.0), (0.2, 0.0, 0.0), (0.0, 0.0, 0.05)])
def test_kernel_equals_the_torch_function_and_the_reference_on_shared_table_views(compiled, monkeypatch, dtype,
                                                                                     weights):
    field = _field(dtype)
    planes = _planes(field)
    assert shared_table(planes, field.layout) is not None and planes[0].stride()[1] == 1  # channels-last views
    got = _kernel_value_and_grads(monkeypatch, field.grids, weights)
    _assert_matches(got, _value_and_grads(_torch_function, field.grids, weights), dtype)
    _assert_matches(got, _value_and_grads(hexplane_regularization_reference, field.grids, weights), dtype)
    assert got[0].dtype == dtype and got[0].item() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_equals_the_torch_function_on_plain_permuted_and_expanded_planes(compiled, monkeypatch, dtype):
    g = torch.Generator().manual_seed(1)

    def rand(*shape):
        return torch.randn(*shape, generator=g, dtype=dtype) + 1.0

    level = [
        rand(1, 3, 7, 5),                                    # contiguous
        rand(2, 4, 6, 3),                                    # B = 2
        rand(5, 1, 4, 8).permute(1, 3, 0, 2),                # [1, 8, 5, 4], dense, channels innermost
        rand(1, 3, 7, 6).transpose(2, 3),                    # [1, 3, 6, 7], dense, H innermost: strided rows
        rand(1, 3, 1, 6).expand(1, 3, 4, 6),                 # overlapping (stride 0 along H): a copy is regularised
        rand(1, 3, 10, 12)[..., 1:9, ::2],                   # sliced, not dense
    ]
    levels = [[p.requires_grad_() if p.is_leaf else p for p in level]]
    leaves = [p for p in levels[0]]
    for weights in (WEIGHTS, (0.5, 0.25, 0.125)):
        got = _kernel_value_and_grads(monkeypatch, levels, weights)
        _assert_matches(got, _value_and_grads(_torch_function, levels, weights), dtype)
        # the gradients have the planes' shapes; a dense plane's gradient has its strides too
        assert [tuple(x.shape) for x in got[1]] == [tuple(p.shape) for p in leaves]
    value = hexplane_regularization(levels, *WEIGHTS)
    for permuted in levels[0][2:4]:
        assert torch.autograd.grad(value, [permuted], retain_graph=True)[0].stride() == permuted.stride()


def test_planes_too_short_for_a_second_difference_and_zero_weights(compiled, monkeypatch):
    # time resolution 2: the time planes have H = 2, no smoothness; the spatial ones do have it
    field = _field(torch.float64, resolution=[4, 5, 6, 2], seed=2)
    for weights in (WEIGHTS, (0.7, 0.0, 0.0)):
        got = _kernel_value_and_grads(monkeypatch, field.grids, weights)
        _assert_matches(got, _value_and_grads(hexplane_regularization_reference, field.grids, weights), torch.float64)
    # smoothness of the time planes only, which are too short: zero, and no gradient at all
    value, grads = _kernel_value_and_grads(monkeypatch, field.grids, (0.7, 0.0, 0.0))
    assert value.item() == 0.0 and all(bool((g == 0).all()) for g in grads)
    # all weights zero: zero, no plane gets a gradient (as the torch Function)
    monkeypatch.setenv(regularization_kernel.ENV_SWITCH, "1")
    planes = _planes(field)
    value = hexplane_regularization(field.grids, 0.0, 0.0, 0.0)
    assert value.item() == 0.0
    assert torch.autograd.grad(value, planes, allow_unused=True) == tuple([None] * len(planes))


def test_planes_at_exactly_one_have_no_l1_gradient(compiled, monkeypatch):
    ones = torch.ones(1, 4, 5, 6, dtype=torch.float64, requires_grad=True)
    mixed = torch.ones(1, 4, 5, 6, dtype=torch.float64)
    mixed[0, 0, :2] = 3.0
    mixed[0, 1, :2] = -1.0
    mixed.requires_grad_()
    level = [torch.rand(1, 4, 5, 6, dtype=torch.float64, requires_grad=True) for _ in range(6)]
    level[2], level[4] = ones, mixed
    value, grads = _kernel_value_and_grads(monkeypatch, [level], (0.0, 0.5, 0.0))  # L1 of the time planes only
    assert value.item() == pytest.approx(0.5 * (2 * 12 * 2.0) / 120 + 0.5 * (level[5] - 1).abs().mean().item())
    assert bool((grads[2] == 0).all())                           # sign(0) = 0, as autograd's abs
    step = 0.5 / 120
    expected = torch.zeros_like(mixed)
    expected[0, 0, :2], expected[0, 1, :2] = step, -step
    assert torch.equal(grads[4], expected)
    assert all(bool((grads[k] == 0).all()) for k in (0, 1, 3))  # spatial planes: no L1 term


def test_kernel_passes_gradcheck(compiled, monkeypatch):
    monkeypatch.setenv(regularization_kernel.ENV_SWITCH, "1")
    g = torch.Generator().manual_seed(3)
    # values away from the L1 kink at 1 (finite differences must not cross it)
    planes = [(torch.rand(1, 2, h, w, generator=g, dtype=torch.float64) + 1.5).requires_grad_()
              for h, w in ((5, 4), (4, 3), (6, 4), (3, 5), (6, 3), (2, 6))]

    def total(*ps):
        return hexplane_regularization([list(ps)], 0.3, 0.2, 0.1)

    assert torch.autograd.gradcheck(total, planes, eps=1e-6, atol=1e-8, rtol=1e-6)


def test_incoming_gradient_accumulation_and_a_retained_graph(compiled, monkeypatch):
    field = _field(torch.float64, seed=4)
    planes = _planes(field)
    monkeypatch.setenv(regularization_kernel.ENV_SWITCH, "0")
    want = torch.autograd.grad(hexplane_regularization(field.grids, *WEIGHTS), planes)
    monkeypatch.setenv(regularization_kernel.ENV_SWITCH, "1")
    value = hexplane_regularization(field.grids, *WEIGHTS)
    (3.0 * value).backward(retain_graph=True)      # scaled incoming gradient, into empty .grad
    (value * 1.0).backward(retain_graph=True)      # accumulated into the first .grad
    value.backward()                               # a third pass through the retained graph
    for plane, w in zip(planes, want):
        torch.testing.assert_close(plane.grad, 5.0 * w, rtol=1e-12, atol=1e-15)
    # a plane changed in place after the forward: the backward refuses, as the torch Function's
    value = hexplane_regularization(field.grids, *WEIGHTS)
    with torch.no_grad():
        planes[0].add_(1.0)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        value.backward()


def test_no_gradient_wanted_gives_the_same_value_without_computing_gradients(compiled, monkeypatch):
    field = _field(torch.float32, seed=5)
    monkeypatch.setenv(regularization_kernel.ENV_SWITCH, "1")
    wanted = []
    run_kernel = regularization_kernel.run_kernel

    def spy(planes, smooth, l1, need_grad, num_threads=None):
        wanted.append(any(need_grad))
        return run_kernel(planes, smooth, l1, need_grad, num_threads)

    monkeypatch.setattr(regularization_kernel, "run_kernel", spy)
    with_graph = hexplane_regularization(field.grids, *WEIGHTS)
    with torch.no_grad():
        without = hexplane_regularization(field.grids, *WEIGHTS)
    detached = hexplane_regularization([[p.detach() for p in level] for level in field.grids], *WEIGHTS)
    assert without.grad_fn is None and torch.equal(without, with_graph.detach())
    assert detached.grad_fn is None and torch.equal(detached, without)
    assert wanted == [True, False, False]


def test_results_do_not_depend_on_the_thread_count(compiled):
    g = torch.Generator().manual_seed(6)
    # 16 x 300 x 40 = 192k values per plane: several row blocks of the kernel's 65536 values
    planes = [torch.randn(1, 16, 300, 40, generator=g) + 1.0 for _ in range(3)]
    smooth, l1 = [0.3, 0.01, 0.2], [0.0, 0.05, 0.1]
    results = [regularization_kernel.run_kernel(planes, smooth, l1, [True] * 3, num_threads=t) for t in (1, 3)]
    (v1, g1), (v3, g3) = results
    assert v1 == v3
    assert all(torch.equal(a, b) for a, b in zip(g1, g3))
    # and the blocks agree with the torch Function (block edges recompute the rows of s before them)
    leaves = [p.clone().requires_grad_() for p in planes]
    want = _WeightedPlaneRegularisation.apply(tuple(smooth), tuple(l1), *leaves)
    torch.testing.assert_close(torch.tensor(v1, dtype=torch.float32), want.detach(), rtol=1e-5, atol=0)
    for a, b in zip(g1, torch.autograd.grad(want, leaves)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-9)


def test_dispatch_and_fallbacks(compiled, monkeypatch, caplog):
    field = _field(torch.float32, seed=7)
    assert type(hexplane_regularization(field.grids, *WEIGHTS).grad_fn).__name__ == "_KernelRegularisationBackward"
    monkeypatch.setattr(regularization_kernel, "_logged_reasons", set())
    with caplog.at_level(logging.INFO, logger=regularization_kernel.__name__):
        for name in (regularization_kernel.ENV_SWITCH, regularization_kernel.ENV_ALL_KERNELS):
            monkeypatch.setenv(name, "off")
            for _ in range(2):  # logged once per reason
                value = hexplane_regularization(field.grids, *WEIGHTS)
                assert type(value.grad_fn).__name__ == "_WeightedPlaneRegularisationBackward"
            monkeypatch.delenv(name)
        # other dtypes take the torch Function
        half = [[p.detach().to(torch.bfloat16).requires_grad_() for p in level] for level in field.grids]
        assert type(hexplane_regularization(half, *WEIGHTS).grad_fn).__name__ == "_WeightedPlaneRegularisationBackward"
    records = [r for r in caplog.records if r.name == regularization_kernel.__name__]
    assert len(records) == 3 and all(r.levelno == logging.INFO for r in records)


def test_missing_compiler_falls_back_to_the_torch_function(monkeypatch, tmp_path, caplog):
    monkeypatch.setenv(native_build.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.setenv("CXX", "no-such-compiler-reflow4dgs")
    monkeypatch.setattr(regularization_kernel, "_logged_reasons", set())
    regularization_kernel.LIBRARY.reset()
    try:
        field = _field(torch.float32, seed=8)
        with caplog.at_level(logging.INFO, logger=regularization_kernel.__name__):
            got = hexplane_regularization(field.grids, *WEIGHTS)
            hexplane_regularization(field.grids, *WEIGHTS)
        assert type(got.grad_fn).__name__ == "_WeightedPlaneRegularisationBackward"
        assert torch.equal(got, _torch_function(field.grids, *WEIGHTS))
        records = [r for r in caplog.records if r.name == regularization_kernel.__name__]
        assert len(records) == 1 and records[0].levelno == logging.WARNING
        assert "no C++ compiler" in records[0].getMessage()
    finally:
        regularization_kernel.LIBRARY.reset()
