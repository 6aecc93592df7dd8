"""What is specific to the compiled CPU compositor (baselines/render/kernel.py + csrc/).

Its values and gradients against the dense reference are tested with every other CPU compositor
by the shared parametrised tests (tests/raster_cases.py: CPU_COMPOSITORS): test_raster_backends.py,
test_raster_hard_cases.py and test_raster_handworked.py. Here: compiled binning == torch binning,
bitwise determinism across thread counts and across the AVX2 and portable variants, the fast exp
(its accuracy, and alpha decisions at the thresholds taken as with the C library's expf), the
environment switches and the fallback to the torch tiled path, and building, caching and failing
to build the library.
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

from baselines import native_build
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
# Instruction-set variants and the fast exp


def _require_avx2():
    if not kernel.isa_supported("avx2"):
        pytest.skip("this CPU has no AVX2; only the portable variant runs")


@pytest.mark.parametrize("case", ["deep_500g_40x23_c3", "needles_and_giants", "stack_1000_depth_ties"])
def test_avx2_and_portable_variants_are_bitwise_identical(compiled, monkeypatch, case):
    # Both variants run the same IEEE operations in the same order (lanes, sums, exp), so where
    # the build machine has AVX2, the portable fallback is exercised by this comparison.
    _require_avx2()
    runs = {}
    for isa in ("portable", "avx2"):
        monkeypatch.setenv(kernel.ENV_ISA, isa)
        assert kernel.kernel_isa(torch.float32) == isa
        runs[isa] = composite_grads(kernel.composite_kernel, named_scene(case))
    for key, value in runs["portable"].items():
        assert torch.equal(value, runs["avx2"][key]), f"{key} differs between the portable and AVX2 variants"


def _colour_loss_grads(scene, read: slice) -> dict[str, torch.Tensor]:
    """Gradients of a loss that reads the channels `read` of the image (and the alpha map), the
    densification statistic's pass beside a plugin's channels."""
    scene = scene.to(scene.means.dtype).requires_grad_()
    proj = project(scene)
    proj.means2d.retain_grad()
    proj.conics.retain_grad()
    image, alpha = kernel.composite_kernel(proj, scene.opacities, scene.features, scene.width, scene.height)
    weights = torch.linspace(-1.0, 2.0, image[..., read].numel()).reshape(image[..., read].shape)
    ((image[..., read] * weights).sum() + (alpha * alpha).sum()).backward()
    out = {"means2d": proj.means2d.grad, "conics": proj.conics.grad}
    out.update({k: v.grad for k, v in scene.gaussian_tensors.items()})
    return out


@pytest.mark.parametrize("read", [slice(0, 3), slice(0, 0), slice(2, 3), slice(0, 8)], ids=["colours", "alpha only",
                                                                                           "one channel", "all"])
def test_channels_without_upstream_gradient_are_left_out_exactly(compiled, monkeypatch, read):
    # A trailing channel whose upstream gradient is zero contributes exact zeros to every sum the
    # backward forms: leaving it out must give bitwise the same gradients, its own being zero.
    scene = random_scene(3000, 96, 64, channels=8, seed=4, pixel_sigma=(1.0, 6.0))
    image = torch.zeros(64, 96, 8)
    image[..., read] = 1.0
    expected = max(1, read.stop)
    assert kernel.active_channels(image) == expected
    monkeypatch.setenv(kernel.ENV_ACTIVE_CHANNELS, "0")
    every = _colour_loss_grads(scene, read)
    monkeypatch.delenv(kernel.ENV_ACTIVE_CHANNELS)
    active = _colour_loss_grads(scene, read)
    for key, value in every.items():
        assert torch.equal(value, active[key]), f"{key} differs when zero-gradient channels are left out"
    assert not active["features"][:, expected:].any()
    assert active["means2d"].abs().sum() > 0


def test_isa_switch_is_validated_and_float64_runs_portable(compiled, monkeypatch):
    monkeypatch.setenv(kernel.ENV_ISA, "avx512")
    with pytest.raises(ValueError, match=kernel.ENV_ISA):
        kernel.kernel_isa()
    monkeypatch.setenv(kernel.ENV_ISA, "auto")
    assert kernel.kernel_isa(torch.float64) == "portable"
    assert kernel.kernel_isa(torch.float32) == ("avx2" if kernel.isa_supported("avx2") else "portable")


def _raw_alpha(sigma: torch.Tensor, opacity: torch.Tensor, isa: str) -> torch.Tensor:
    """o exp(-sigma) in float32 as the compositor computes it, with the given variant."""
    sigma, opacity = sigma.float().contiguous(), opacity.float().contiguous()
    out = torch.empty_like(sigma)
    status = kernel.load_library().rk_raw_alpha_f32(sigma.data_ptr(), opacity.data_ptr(), out.data_ptr(),
                                                    sigma.numel(), kernel.ISA_CODES[isa])
    assert status == 0
    return out


def _libm_raw_alpha(sigma: torch.Tensor, opacity: torch.Tensor) -> torch.Tensor:
    """o expf(-sigma) with the C library's expf, the product rounded to float32."""
    x = (-sigma).float().contiguous()
    vis = torch.empty_like(x)
    kernel.load_library().rk_libm_expf(x.data_ptr(), vis.data_ptr(), x.numel())
    return opacity.float() * vis


def _isas() -> list[str]:
    return ["portable", "avx2"] if kernel.isa_supported("avx2") else ["portable"]


def test_fast_exp_is_within_one_ulp_of_the_c_library(compiled):
    g = torch.Generator().manual_seed(0)
    sigma = torch.rand(200_000, generator=g) * 5.6  # the range alpha >= 1/255 allows
    opacity = torch.ones_like(sigma)
    want = _libm_raw_alpha(sigma, opacity)
    ulp = torch.nextafter(want, torch.tensor(float("inf"))) - want
    for isa in _isas():
        got = _raw_alpha(sigma, opacity, isa)
        assert ((got - want).abs() <= ulp).all(), f"{isa}: the fast exp is off by more than 1 ulp"
    assert torch.equal(_raw_alpha(torch.zeros(9), torch.full((9,), 0.5), "portable"), torch.full((9,), 0.5))


@pytest.mark.parametrize("threshold", [1.0 / 255.0, 0.999])
def test_alpha_decisions_at_the_thresholds_are_those_of_the_c_library_expf(compiled, threshold):
    # sigma within +-16 float steps of ln(o / threshold), so that o exp(-sigma) lands within a few
    # ulp of the threshold on both sides; the fast exp alone (about 1 ulp off in 5% of values)
    # would flip some of these decisions, the expf recomputation in the band must not.
    t = torch.tensor(threshold, dtype=torch.float32)
    g = torch.Generator().manual_seed(1)
    low = float(t) * 1.0001
    opacity = (low + (1.0 - low) * torch.rand(4000, generator=g)).float()
    centre = torch.log(opacity.double() / float(t)).float()
    ulp = torch.nextafter(centre, torch.tensor(float("inf"))) - centre
    sigma = centre[:, None] + torch.arange(-16, 17, dtype=torch.float32) * ulp[:, None]
    opacity = opacity[:, None].expand_as(sigma).contiguous()
    sigma = sigma.clamp(min=0).contiguous()
    want = _libm_raw_alpha(sigma, opacity)
    below = want < t if threshold < 0.5 else want > t  # skipped / clamped by the exact expf
    assert below.any() and (~below).any()
    for isa in _isas():
        got = _raw_alpha(sigma, opacity, isa)
        got_below = got < t if threshold < 0.5 else got > t
        assert torch.equal(got_below, below), f"{isa}: {int((got_below != below).sum())} decisions differ"


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
    monkeypatch.setattr(kernel.LIBRARY, "_library", None)
    monkeypatch.setattr(kernel.LIBRARY, "_load_error", None)
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
    slow = tmp_path / "slow-c++"
    slow.write_text(f'#!/bin/sh\nsleep 0.3\nexec "{compiler}" "$@"\n')
    slow.chmod(0o755)
    target = fresh_kernel_state / "raster_kernel-race.so"
    errors: list = []

    def build():
        try:
            native_build.build(str(slow), source, target)
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
    # `compiled` is the library the test session built or found; copy it into the empty cache.
    target = kernel.library_path(kernel.find_compiler())
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(compiled, target)

    def no_build(*args):
        raise AssertionError("rebuilt although the cache holds the library")

    monkeypatch.setattr(kernel.LIBRARY, "build", no_build)
    ok, path = kernel.kernel_available()
    assert ok and Path(path) == target


def test_unsupported_dtype_falls_back():
    assert "bfloat16" in kernel.unusable_reason(torch.zeros(2, 3, dtype=torch.bfloat16))


def test_kernel_rejects_mixed_dtypes(compiled):
    scene = random_scene(10, 16, 16)
    with pytest.raises(ValueError, match="features"):
        kernel.composite_kernel(project(scene), scene.opacities, scene.features.double(), 16, 16)
