"""What is specific to the compiled CPU compositor (baselines/render/kernel.py + csrc/).

Its values and gradients against the dense reference are tested with every other CPU compositor
by the shared parametrised tests (tests/raster_cases.py: CPU_COMPOSITORS): test_raster_backends.py,
test_raster_hard_cases.py and test_raster_handworked.py. Here: compiled binning == torch binning,
bitwise determinism across thread counts, the environment switch and the fallback to the torch
tiled path, and building, caching and failing to build the library.
"""
from __future__ import annotations

import ctypes
import logging
import shutil
import sys
import threading
import types
from pathlib import Path

import pytest
import torch

from baselines.render import kernel, rasterize
from baselines.render.composite_reference import composite_reference
from baselines.render.tiles import bin_gaussians
from raster_cases import HARD_CASES, VALUE_ATOL, composite_grads, named_scene, project, random_scene


@pytest.fixture(scope="module")
def compiled():
    """The built library's path. Skips when the kernel is switched off or there is no C++
    compiler; a failing build fails."""
    ok, reason = kernel.kernel_available()
    if not ok and (kernel.disabled_by_env() or kernel.find_compiler() is None):
        pytest.skip(reason)
    assert ok, reason
    return Path(reason)


def test_kernel_builds_where_a_compiler_is_present(compiled):
    # The shared tests skip the kernel whenever it is unavailable; this is where a broken build
    # (a compiler present, the source not compiling) fails instead of going unnoticed.
    assert compiled.is_file()


# ---------------------------------------------------------------------------------------------
# Binning and determinism


@pytest.mark.parametrize("case", ["random_2000", *HARD_CASES])
def test_compiled_binning_equals_torch_binning(compiled, case):
    scene = random_scene(2000, 150, 97, channels=1, seed=9) if case == "random_2000" else named_scene(case)
    proj = project(scene)
    want = bin_gaussians(proj, scene.width, scene.height)
    got = kernel.bin_gaussians_compiled(proj, scene.width, scene.height)
    assert (got.tiles_x, got.tiles_y) == (want.tiles_x, want.tiles_y)
    assert torch.equal(got.offsets, want.offsets)
    assert torch.equal(got.gaussian_ids, want.gaussian_ids)


def test_bitwise_identical_across_thread_counts(compiled):
    scene = random_scene(4000, 120, 90, channels=4, seed=5, pixel_sigma=(1.0, 6.0))
    runs = [composite_grads(lambda *args, t=t: kernel.composite_kernel(*args, num_threads=t), scene)
            for t in (1, 2, 3, 2)]
    for run in runs[1:]:
        for key, value in runs[0].items():
            assert torch.equal(value, run[key]), f"{key} differs between thread counts"


# ---------------------------------------------------------------------------------------------
# Fallback to the torch tiled path, build and cache


def _fake_tiled_module(calls: list) -> types.ModuleType:
    module = types.ModuleType("baselines.render.composite_tiled")

    def composite_tiled(projection, opacities, features, width, height):
        calls.append(features.shape)
        return composite_reference(projection, opacities, features, width, height)

    module.composite_tiled = composite_tiled
    return module


def test_env_var_forces_torch_path_and_logs_once(monkeypatch, caplog):
    # (The real torch tiled path behind the switch is compared with the reference, end to end, in
    # test_raster_backends.py::test_public_rasterize_cpu_matches_reference[torch_tiled].)
    calls: list = []
    monkeypatch.setitem(sys.modules, "baselines.render.composite_tiled", _fake_tiled_module(calls))
    monkeypatch.setenv(kernel.ENV_SWITCH, "0")
    monkeypatch.setattr(kernel, "_logged_reasons", set())

    def must_not_run(*args, **kwargs):
        raise AssertionError("the compiled kernel ran although it is disabled")

    monkeypatch.setattr(kernel, "composite_kernel", must_not_run)
    assert kernel.kernel_available() == (False, kernel.disabled_by_env())
    scene = random_scene(100, 40, 30, seed=2)
    with caplog.at_level(logging.INFO, logger=kernel.__name__):
        for _ in range(2):
            assert rasterize(*scene.args(), backend="cpu")[3].backend == "cpu"
    assert len(calls) == 2 and calls[0][1] == 4  # 3 features + the depth channel
    records = [r for r in caplog.records if r.name == kernel.__name__]
    assert len(records) == 1 and records[0].levelno == logging.INFO and kernel.ENV_SWITCH in records[0].getMessage()


@pytest.fixture
def fresh_kernel_state(monkeypatch, tmp_path):
    """Forget the loaded library and point the cache at an empty directory."""
    monkeypatch.setattr(kernel, "_library", None)
    monkeypatch.setattr(kernel, "_load_error", None)
    monkeypatch.setenv(kernel.ENV_CACHE_DIR, str(tmp_path / "cache"))
    monkeypatch.delenv(kernel.ENV_SWITCH, raising=False)
    return tmp_path / "cache"


def test_missing_compiler_is_reported_and_falls_back_with_one_warning(fresh_kernel_state, monkeypatch, caplog):
    monkeypatch.setenv("CXX", "no-such-compiler-reflow4dgs")
    monkeypatch.setattr(kernel, "_logged_reasons", set())
    ok, reason = kernel.kernel_available()
    assert not ok and "no C++ compiler" in reason and "no-such-compiler-reflow4dgs" in reason
    assert kernel.unusable_reason(torch.zeros(1, 3)) == reason
    scene = random_scene(30, 20, 16, seed=1)
    with caplog.at_level(logging.INFO, logger=kernel.__name__):
        for _ in range(2):
            image, _, alpha, _ = rasterize(*scene.args(), backend="cpu")
    want_image, _, want_alpha, _ = rasterize(*scene.args(), backend="reference")
    torch.testing.assert_close(image, want_image, atol=VALUE_ATOL, rtol=0)
    torch.testing.assert_close(alpha, want_alpha, atol=VALUE_ATOL, rtol=0)
    records = [r for r in caplog.records if r.name == kernel.__name__]
    assert len(records) == 1 and records[0].levelno == logging.WARNING and reason in records[0].getMessage()


def test_failing_build_is_reported_and_attempted_once(fresh_kernel_state, monkeypatch, tmp_path):
    fake = tmp_path / "broken-c++"
    fake.write_text("#!/bin/sh\necho 'fatal: simulated compiler failure' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CXX", str(fake))
    ok, reason = kernel.kernel_available()
    assert not ok and "simulated compiler failure" in reason
    fake.unlink()  # a second call must reuse the recorded failure, not run the compiler again
    assert kernel.kernel_available() == (False, reason)
    assert not any(fresh_kernel_state.glob("*.so")) and not any(fresh_kernel_state.glob(".build-*"))


def test_concurrent_builds_leave_one_valid_library(fresh_kernel_state, monkeypatch, tmp_path):
    # Two builders racing on the same cache entry (as two processes on first use would): each
    # compiles in its own temporary directory and renames atomically, so the survivor is whole.
    # A one-function source keeps this fast; a compiler wrapper that sleeps first makes the two
    # compilations overlap for certain.
    compiler = kernel.find_compiler()
    if compiler is None:
        pytest.skip("no C++ compiler")
    source = tmp_path / "tiny.cpp"
    source.write_text('extern "C" int rk_abi_version() { return 7; }\n')
    monkeypatch.setattr(kernel, "SOURCE", source)
    slow = tmp_path / "slow-c++"
    slow.write_text(f'#!/bin/sh\nsleep 0.3\nexec "{compiler}" "$@"\n')
    slow.chmod(0o755)
    target = fresh_kernel_state / "raster_kernel-race.so"
    errors: list = []

    def build():
        try:
            kernel._build(str(slow), target)
        except Exception as exc:  # reported below
            errors.append(exc)

    workers = [threading.Thread(target=build) for _ in range(2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    assert not errors
    assert list(fresh_kernel_state.iterdir()) == [target]  # no temporary leftovers
    assert ctypes.CDLL(str(target)).rk_abi_version() == 7


def test_cached_library_is_loaded_without_rebuilding(compiled, fresh_kernel_state, monkeypatch):
    # `compiled` is the library this session built or found; copy it into the empty cache.
    target = kernel.library_path(kernel.find_compiler())
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(compiled, target)

    def no_build(*args):
        raise AssertionError("rebuilt although the cache holds the library")

    monkeypatch.setattr(kernel, "_build", no_build)
    ok, path = kernel.kernel_available()
    assert ok and Path(path) == target


def test_unsupported_dtype_falls_back():
    assert "bfloat16" in kernel.unusable_reason(torch.zeros(2, 3, dtype=torch.bfloat16))


def test_kernel_rejects_mixed_dtypes(compiled):
    scene = random_scene(10, 16, 16)
    with pytest.raises(ValueError, match="features"):
        kernel.composite_kernel(project(scene), scene.opacities, scene.features.double(), 16, 16)
