"""Compiled HexPlane lookup (baselines/fourdgs/plane_kernel.py) against the torch path of plane_lookup.

The torch path is the oracle (itself tested against grid_sample in test_hexplane.py, which runs
both paths). Covered: values and gradients of table, space and time for HexPlane layouts and odd
shapes (1-wide and 1-high planes, channel counts with and without a vector tail and the
specialised 8/16/32), clamped and boundary coordinates, partial gradient requests, bitwise
determinism across thread counts (several backward chunks), gradcheck, and the fallbacks.
"""
from __future__ import annotations

import logging

import pytest
import torch

from baselines import native_build
from baselines.fourdgs import plane_kernel
from baselines.fourdgs.hexplane import PLANE_AXES, HexPlaneField
from baselines.fourdgs.plane_lookup import PlaneLayout, plane_product_lookup, planes_to_table


@pytest.fixture(scope="module")
def compiled():
    ok, reason = plane_kernel.LIBRARY.available()
    if not ok and native_build.find_compiler() is None:
        pytest.skip(reason)
    assert ok, reason  # a compiler is present: the kernel must build
    return ok


def _hexplane_layout(resolution: list[int], levels: list[int]) -> PlaneLayout:
    sizes = []
    for multiplier in levels:
        res = [r * multiplier for r in resolution[:3]] + resolution[3:]
        sizes += [(res[b], res[a]) for a, b in PLANE_AXES]
    return PlaneLayout.build(sizes, list(PLANE_AXES) * len(levels), len(PLANE_AXES))


def _coordinates(n: int, dtype: torch.dtype, seed: int) -> torch.Tensor:
    """[n, 4] in [-1.2, 1.2] (some clamped), with exact borders and centres among them."""
    g = torch.Generator().manual_seed(seed)
    coords = torch.rand(n, 4, generator=g, dtype=dtype) * 2.4 - 1.2
    special = torch.tensor([-1.0, 1.0, 0.0, -1.0 + 1e-7, 1.0 - 1e-7], dtype=dtype)
    coords[: len(special), 0] = special
    coords[: len(special), 3] = special.flip(0)
    return coords


def _lookup(engine: str, monkeypatch, table, layout, space, time):
    monkeypatch.setenv(plane_kernel.ENV_SWITCH, "1" if engine == "kernel" else "0")
    return plane_product_lookup(table, layout, space, time)


def _values_and_grads(engine, monkeypatch, table, layout, coords, need_time=True, seed=0):
    table = table.detach().clone().requires_grad_()
    space = coords[:, :3].clone().requires_grad_()
    time = coords[:, 3:].clone().requires_grad_(need_time)
    out = _lookup(engine, monkeypatch, table, layout, space, time)
    weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=out.dtype)
    inputs = [table, space] + ([time] if need_time else [])
    return out, torch.autograd.grad((out * weights).sum(), inputs)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [16, 5, 32, 1])
def test_kernel_equals_torch_path_on_hexplane_layouts(compiled, monkeypatch, dtype, channels):
    layout = _hexplane_layout([6, 5, 4, 3], [1, 2])
    table = torch.rand(layout.num_cells, channels, dtype=dtype, generator=torch.Generator().manual_seed(channels)) * 2 - 0.5
    coords = _coordinates(700, dtype, seed=channels)
    want, want_grads = _values_and_grads("torch", monkeypatch, table, layout, coords)
    got, got_grads = _values_and_grads("kernel", monkeypatch, table, layout, coords)
    tol = {"rtol": 1e-5, "atol": 1e-6} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    # A coordinate's gradient sums channels x corners x planes float32 products; the two paths (and
    # torch's own reductions, whose order depends on the threads free at the time) add them in
    # different orders, so a near-zero sum of O(1) terms differs by a few ulps of the TERMS: measured
    # up to 1.9e-6 on a loaded 2-core machine, 1.7e-5 with 32 channels (a random table drawn after
    # other tests): the rounding grows with the terms summed, so the bound scales with the channels.
    # Values sum a few corners per plane: the tight bound holds.
    grad_tol = {"rtol": 1e-5, "atol": 1e-6 * max(10, channels)} if dtype == torch.float32 else tol
    torch.testing.assert_close(got, want, **tol)
    for name, g, w in zip(("table", "space", "time"), got_grads, want_grads):
        torch.testing.assert_close(g, w, **grad_tol, msg=lambda m, name=name: f"{name} gradient: {m}")


def test_kernel_handles_one_wide_and_one_high_planes_and_groups_of_one(compiled, monkeypatch):
    sizes = [(1, 6), (6, 1), (1, 1), (7, 9)]
    axes = [(0, 1), (1, 2), (0, 2), (2, 0)]
    layout = PlaneLayout.build(sizes, axes, 1)
    table = torch.randn(layout.num_cells, 8, dtype=torch.float64)
    coords = _coordinates(300, torch.float64, seed=3)[:, :3]
    space = coords.clone().requires_grad_()
    results = []
    for engine in ("torch", "kernel"):
        t = table.clone().requires_grad_()
        s = space.detach().clone().requires_grad_()
        out = _lookup(engine, monkeypatch, t, layout, s, None)
        results.append((out, *torch.autograd.grad(out.square().sum(), [t, s])))
    for got, want in zip(results[1], results[0]):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_kernel_gives_only_the_requested_gradients(compiled, monkeypatch):
    layout = _hexplane_layout([4, 4, 4, 3], [1])
    table = torch.rand(layout.num_cells, 4, dtype=torch.float64)
    coords = _coordinates(200, torch.float64, seed=5)
    want, want_grads = _values_and_grads("torch", monkeypatch, table, layout, coords, need_time=False)
    got, got_grads = _values_and_grads("kernel", monkeypatch, table, layout, coords, need_time=False)
    assert len(got_grads) == 2
    for g, w in zip(got_grads, want_grads):
        torch.testing.assert_close(g, w, rtol=1e-12, atol=1e-12)
    # table only (no coordinate wants a gradient)
    grad_table, grad_coords = plane_kernel.lookup_backward(table, coords, layout, torch.ones(200, 4, dtype=torch.float64),
                                                           [False] * 4, True)
    assert grad_coords is None and grad_table.shape == table.shape and grad_table.abs().sum() > 0


def test_kernel_backward_is_bitwise_identical_for_any_thread_count(compiled):
    # more points than one backward chunk (8192), so the two-phase path runs several chunks
    layout = _hexplane_layout([8, 8, 8, 5], [1, 2])
    table = torch.rand(layout.num_cells, 16)
    coords = _coordinates(20_000, torch.float32, seed=7)
    grad_out = torch.randn(20_000, 32, generator=torch.Generator().manual_seed(1))
    results = [plane_kernel.lookup_backward(table, coords, layout, grad_out, [True] * 4, True, num_threads=k)
               for k in (1, 2, 3)]
    forwards = [plane_kernel.lookup_forward(table, coords, layout, num_threads=k) for k in (1, 3)]
    for grad_table, grad_coords in results[1:]:
        assert torch.equal(grad_table, results[0][0]) and torch.equal(grad_coords, results[0][1])
    assert torch.equal(forwards[0], forwards[1])


def test_kernel_passes_gradcheck(compiled, monkeypatch):
    monkeypatch.setenv(plane_kernel.ENV_SWITCH, "1")
    layout = _hexplane_layout([3, 4, 3, 2], [1])
    table = torch.rand(layout.num_cells, 3, dtype=torch.float64, requires_grad=True)
    # away from cell edges, where the bilinear lookup is not differentiable
    space = (torch.rand(6, 3, dtype=torch.float64) * 1.6 - 0.8).requires_grad_()
    time = (torch.rand(6, 1, dtype=torch.float64) * 1.6 - 0.8).requires_grad_()
    assert torch.autograd.gradcheck(lambda t, s, u: plane_product_lookup(t, layout, s, u), (table, space, time))


def test_hexplane_field_trains_the_same_on_both_paths(compiled, monkeypatch):
    config = {"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 16, "resolution": [8, 8, 8, 4]}
    results = []
    for engine in ("torch", "kernel"):
        monkeypatch.setenv(plane_kernel.ENV_SWITCH, "1" if engine == "kernel" else "0")
        torch.manual_seed(0)
        field = HexPlaneField(1.0, config, [1, 2])
        optimizer = torch.optim.Adam(field.parameters(), lr=1e-2)
        pts = torch.rand(500, 3) * 2 - 1
        times = torch.rand(500, 1)
        target = torch.randn(500, field.feat_dim)
        for _ in range(5):
            optimizer.zero_grad()
            (field(pts, times) - target).square().mean().backward()
            optimizer.step()
        results.append(torch.cat([p.detach().flatten() for p in field.parameters()]))
    torch.testing.assert_close(results[1], results[0], rtol=1e-4, atol=1e-5)


def test_switch_and_unsupported_tensors_take_the_torch_path(monkeypatch, caplog):
    layout = _hexplane_layout([4, 4, 4, 3], [1])
    table = planes_to_table([torch.rand(1, 2, h, w) for h, w in zip(layout.height, layout.width)])
    coords = _coordinates(50, torch.float32, seed=2)

    def must_not_run(*args, **kwargs):
        raise AssertionError("the compiled lookup ran although switched off")

    monkeypatch.setattr(plane_kernel, "lookup_forward", must_not_run)
    monkeypatch.setattr(plane_kernel, "_logged_reasons", set())
    for value in ("0", "off"):
        monkeypatch.setenv(plane_kernel.ENV_SWITCH, value)
        assert plane_product_lookup(table, layout, coords[:, :3], coords[:, 3:]).shape == (50, 2)
    monkeypatch.delenv(plane_kernel.ENV_SWITCH)
    monkeypatch.setenv(plane_kernel.ENV_ALL_KERNELS, "0")  # every compiled CPU kernel off
    assert "REFLOW4DGS_CPU_KERNEL" in plane_kernel.disabled_by_env()
    with caplog.at_level(logging.INFO, logger=plane_kernel.__name__):
        for _ in range(2):
            plane_product_lookup(table, layout, coords[:, :3], coords[:, 3:])
    assert len([r for r in caplog.records if r.name == plane_kernel.__name__]) == 1
    monkeypatch.delenv(plane_kernel.ENV_ALL_KERNELS)
    assert "bfloat16" in plane_kernel.unusable_reason(table.bfloat16(), torch.bfloat16)
    assert "same dtype" in plane_kernel.unusable_reason(table, torch.float64)


def test_missing_compiler_falls_back_with_one_warning(monkeypatch, tmp_path, caplog):
    monkeypatch.setattr(plane_kernel.LIBRARY, "_library", None)
    monkeypatch.setattr(plane_kernel.LIBRARY, "_load_error", None)
    monkeypatch.setattr(plane_kernel, "_logged_reasons", set())
    monkeypatch.setenv(native_build.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.setenv("CXX", "no-such-compiler-reflow4dgs")
    monkeypatch.delenv(plane_kernel.ENV_SWITCH, raising=False)
    monkeypatch.delenv(plane_kernel.ENV_ALL_KERNELS, raising=False)
    layout = _hexplane_layout([4, 4, 4, 3], [1])
    table = torch.rand(layout.num_cells, 3)
    coords = _coordinates(40, torch.float32, seed=4)
    with caplog.at_level(logging.INFO, logger=plane_kernel.__name__):
        for _ in range(2):
            out = plane_product_lookup(table, layout, coords[:, :3], coords[:, 3:])
    monkeypatch.setenv(plane_kernel.ENV_SWITCH, "0")
    torch.testing.assert_close(out, plane_product_lookup(table, layout, coords[:, :3], coords[:, 3:]))
    records = [r for r in caplog.records if r.name == plane_kernel.__name__]
    assert len(records) == 1 and records[0].levelno == logging.WARNING
    assert "no C++ compiler" in records[0].getMessage()
