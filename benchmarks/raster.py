"""Rasterizer speed: forward and forward+backward per implementation, printed as a markdown table.

    python benchmarks/raster.py                                     # default sizes, 1 and 2 threads
    python benchmarks/raster.py --threads 1 2 --repeats 5
    python benchmarks/raster.py --sizes 20000x256x256 --threads 2 --only kernel,torch_tiled
    python benchmarks/raster.py --sizes 2000x128x96:init                # a freshly initialised model

Every implementation renders the same scene through the whole pipeline a training step pays for:
torch projection, compositing of the features plus the depth channel, and (fwd+bwd) the backward
of a fixed random weighting of image, depth and alpha down to means, quats, scales, opacities and
features. "forward" is the training forward (inputs require grad). Implementations:

- reference: rasterize(backend="reference"), the dense oracle; skipped where pixels x Gaussians
  exceeds --reference-max-pairs (it would take minutes and gigabytes);
- torch_tiled: the cpu backend's torch path (composite_tiled);
- kernel: the cpu backend's compiled C++ compositor (composite_kernel);
- cpu: the public rasterize(backend="cpu") (the kernel when it builds, validation included);
- gsplat: rasterize(backend="gsplat") on CUDA, where gsplat and a GPU are present.

Figures are medians over --repeats runs after one warm-up run. The runs of all implementations
are interleaved (one of each in turn), so a change of machine load affects all alike and the
speed-up ratios, taken within one run of this script, stay meaningful on a shared machine.
"CPU ms" is the process CPU time of all threads per call: less sensitive than wall time to
other jobs, but it also counts threads spinning while they wait (OpenMP does so by default:
set OMP_WAIT_POLICY=PASSIVE where other jobs share the cores). The load average is printed at
the start and the end.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()  # before torch: OpenMP waits, threads, allocator (baselines/thread_policy.py)

import torch  # noqa: E402

from baselines.render import kernel, rasterize  # noqa: E402
from machine import cpu_model, load_average  # noqa: E402  (benchmarks/machine.py)
from baselines.render.api import _composite  # noqa: E402
from baselines.render.backends import Backend, gsplat_unavailable_reason  # noqa: E402
from baselines.render.composite_tiled import composite_tiled  # noqa: E402
from baselines.render.projection import project_gaussians_torch  # noqa: E402

DEFAULT_SIZES = "2000x128x128,20000x256x256,100000x512x512,2000x128x96:init"
SCENE_KINDS = ("trained", "init")
PARAMS = ("means", "quats", "scales", "opacities", "features")


@dataclass
class Scene:
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    features: torch.Tensor
    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int

    @property
    def pairs(self) -> int:
        """Pixel x Gaussian pairs: the dense reference's work."""
        return self.means.shape[0] * self.width * self.height

    def leaves(self, device: str) -> "Scene":
        """A copy on `device` whose Gaussian parameters are fresh leaves requiring grad."""
        fresh = {k: getattr(self, k).detach().to(device).requires_grad_(True) for k in PARAMS}
        return Scene(viewmat=self.viewmat.to(device), K=self.K.to(device), width=self.width, height=self.height,
                     **fresh)


def make_scene(n: int, width: int, height: int, seed: int = 0, kind: str = "trained") -> Scene:
    """N Gaussians as a model shows them to a training camera.

    Spread over the view frustum (10% beyond each border) at depths 2..8, anisotropic, randomly
    rotated, RGB features. kind "trained": screen-space standard deviation log-uniform in
    [0.5, 3] px, opacities uniform in [0.05, 0.95] (a trained model). kind "init": standard
    deviation log-uniform in [4, 8] px (radii of about 20 px), opacity 0.1, as a freshly
    initialised model shows them: large, faint, every pixel under hundreds of Gaussians and
    almost none reaching the transmittance stop.
    """
    if kind not in SCENE_KINDS:
        raise ValueError(f"scene kind must be one of {SCENE_KINDS}, got {kind!r}")
    g = torch.Generator().manual_seed(seed)
    f = float(width)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    z = torch.empty(n).uniform_(2.0, 8.0, generator=g)
    u = torch.empty(n).uniform_(-0.1 * width, 1.1 * width, generator=g)
    v = torch.empty(n).uniform_(-0.1 * height, 1.1 * height, generator=g)
    means = torch.stack([(u - K[0, 2]) / f * z, (v - K[1, 2]) / f * z, z], dim=-1)
    sigma_range = (0.5, 3.0) if kind == "trained" else (4.0, 8.0)
    sigma_px = torch.exp(torch.empty(n, 1).uniform_(*(math.log(x) for x in sigma_range), generator=g))
    aniso = torch.exp(torch.empty(n, 3).uniform_(-0.7, 0.7, generator=g))
    opacities = torch.empty(n).uniform_(0.05, 0.95, generator=g) if kind == "trained" else torch.full((n,), 0.1)
    return Scene(means, torch.randn(n, 4, generator=g), sigma_px * aniso * z[:, None] / f, opacities,
                 torch.rand(n, 3, generator=g), torch.eye(4), K, width, height)


Render = Callable[[Scene, int], "tuple[torch.Tensor, ...]"]  # (scene, threads) -> (image, depth, alpha)


@dataclass
class Implementation:
    """One row per scene and thread count: how to render, and whether it can run here."""

    name: str
    render: Render
    device: str = "cpu"
    unavailable: Callable[[], str | None] = lambda: None
    max_pairs: float = math.inf


def from_backend(name: str, backend: str, device: str = "cpu", **kwargs) -> Implementation:
    def render(s: Scene, threads: int):
        return rasterize(s.means, s.quats, s.scales, s.opacities, s.features, s.viewmat, s.K, s.width, s.height,
                         backend=backend)[:3]
    return Implementation(name, render, device, **kwargs)


def from_compositor(name: str, make_compositor: Callable[[int], Callable], **kwargs) -> Implementation:
    """Torch projection + one compositing function, assembled as the public API does."""
    def render(s: Scene, threads: int):
        stage = Backend(name, project_gaussians_torch, make_compositor(threads))
        proj = project_gaussians_torch(s.means, s.quats, s.scales, s.viewmat, s.K, s.width, s.height, s.opacities)
        return _composite(stage, proj, s.opacities, s.features, s.width, s.height, None)
    return Implementation(name, render, **kwargs)


def _kernel_compositor(threads: int):
    def composite(projection, opacities, features, width, height):
        return kernel.composite_kernel(projection, opacities, features, width, height, num_threads=threads)
    return composite


def _kernel_unavailable() -> str | None:
    ok, reason = kernel.kernel_available()
    return None if ok else reason


def implementations(reference_max_pairs: float) -> list[Implementation]:
    return [
        from_backend("reference", "reference", max_pairs=reference_max_pairs),
        from_compositor("torch_tiled", lambda threads: composite_tiled),
        from_compositor("kernel", _kernel_compositor, unavailable=_kernel_unavailable),
        from_backend("cpu", "cpu"),
        from_backend("gsplat", "gsplat", device="cuda",
                     unavailable=lambda: gsplat_unavailable_reason(torch.device("cuda"))),
    ]


# Speed-up columns: (row, baseline) pairs, both measured in the same run.
RATIOS = {"kernel": "torch_tiled", "cpu": "reference"}


@dataclass
class Timings:
    """Per-call samples in seconds (wall and process CPU time), forward and forward+backward."""

    fwd: list[float] = field(default_factory=list)
    both: list[float] = field(default_factory=list)
    fwd_cpu: list[float] = field(default_factory=list)
    both_cpu: list[float] = field(default_factory=list)

    def medians_ms(self) -> tuple[float, float, float, float]:
        return tuple(1e3 * statistics.median(v) for v in (self.fwd, self.both, self.fwd_cpu, self.both_cpu))


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_one_call(impl: Implementation, scene: Scene, threads: int, weights: dict, timings: Timings | None) -> None:
    """Forward and backward of one call; appends to `timings` (None: warm-up, not recorded)."""
    s = scene.leaves(impl.device)
    _sync(impl.device)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    outputs = impl.render(s, threads)
    _sync(impl.device)
    wall1, cpu1 = time.perf_counter(), time.process_time()
    if impl.name not in weights:
        g = torch.Generator().manual_seed(1)
        weights[impl.name] = [torch.randn(o.shape, generator=g).to(o) for o in outputs]
    sum((o * w).sum() for o, w in zip(outputs, weights[impl.name])).backward()
    _sync(impl.device)
    wall2, cpu2 = time.perf_counter(), time.process_time()
    if timings is not None:
        timings.fwd.append(wall1 - wall0)
        timings.both.append(wall2 - wall0)
        timings.fwd_cpu.append(cpu1 - cpu0)
        timings.both_cpu.append(cpu2 - cpu0)


def benchmark_cell(impls: list[Implementation], scene: Scene, threads: int, repeats: int) -> dict[str, Timings]:
    """Interleaved runs (one warm-up, then `repeats` rounds of one call per implementation)."""
    torch.set_num_threads(threads)
    weights: dict = {}
    timings = {impl.name: Timings() for impl in impls}
    for round_index in range(repeats + 1):
        for impl in impls:
            time_one_call(impl, scene, threads, weights, timings[impl.name] if round_index else None)
    return timings


def time_cold_build() -> float:
    """Seconds to compile the kernel into an empty temporary cache (nan without a compiler)."""
    compiler = kernel.find_compiler()
    if compiler is None:
        return float("nan")
    old = os.environ.get(kernel.ENV_CACHE_DIR)
    with tempfile.TemporaryDirectory() as tmp:
        os.environ[kernel.ENV_CACHE_DIR] = tmp
        try:
            target = kernel.library_path(compiler)
            start = time.perf_counter()
            kernel.LIBRARY.build(compiler, target)
            return time.perf_counter() - start
        finally:
            if old is None:
                del os.environ[kernel.ENV_CACHE_DIR]
            else:
                os.environ[kernel.ENV_CACHE_DIR] = old


def _label(scene: Scene, kind: str) -> str:
    n = scene.means.shape[0]
    count = f"{n // 1000}k" if n >= 1000 and n % 1000 == 0 else f"{n}"
    return f"{count}, {scene.width}x{scene.height}" + ("" if kind == "trained" else f", {kind}")


def _speedup(medians: dict, skipped: dict, name: str) -> str:
    baseline = RATIOS.get(name)
    if baseline is None:
        return ""
    if baseline not in medians:
        return f"n/a ({baseline} {'skipped' if baseline in skipped else 'not run'})"
    (bf, bb), (f, b) = medians[baseline][:2], medians[name][:2]
    return f"{bf / f:.1f}x / {bb / b:.1f}x vs {baseline}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default=DEFAULT_SIZES,
                        help="comma-separated NxWIDTHxHEIGHT scenes, each optionally :init (see make_scene)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts, all in this run")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per cell (median reported)")
    parser.add_argument("--reference-max-pairs", type=float, default=5e7,
                        help="skip the dense reference beyond this many pixel x Gaussian pairs")
    parser.add_argument("--only", default="", help="comma-separated implementation names (default: all)")
    parser.add_argument("--compile", action="store_true", help="also time a cold build of the kernel")
    args = parser.parse_args(argv)
    if args.repeats < 1 or min(args.threads) < 1:
        parser.error("--repeats and --threads must be >= 1")
    wanted = {name for name in args.only.split(",") if name}
    impls = [i for i in implementations(args.reference_max_pairs) if not wanted or i.name in wanted]

    ok, where = kernel.kernel_available()
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; torch {torch.__version__}; "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(unset)')}")
    print(f"kernel: {where} ({kernel.kernel_isa()} pixel loops for float32)" if ok else f"kernel: unavailable: {where}")
    if args.compile:
        print(f"cold kernel build: {time_cold_build():.2f} s")
    print(f"load average at start: {load_average('/')} (1/5/15 min)")
    print(f"median of {args.repeats} interleaved calls after one warm-up; ms per call; "
          "speed-up = baseline time / this time (forward / fwd+bwd), same run; the reference is skipped "
          f"beyond {args.reference_max_pairs:.0e} pixel x Gaussian pairs\n")
    print("| scene (N, image) | threads | implementation | forward ms | fwd+bwd ms | forward CPU ms "
          "| fwd+bwd CPU ms | speed-up (fwd / fwd+bwd) |")
    print("|---|---:|---|---:|---:|---:|---:|---|")
    for size in args.sizes.split(","):
        dims, _, kind = size.lower().partition(":")
        kind = kind or "trained"
        n, w, h = (int(v) for v in dims.split("x"))
        scene = make_scene(n, w, h, kind=kind)
        label = _label(scene, kind)
        runnable, skipped = [], {}
        for impl in impls:
            reason = impl.unavailable()
            if reason is None and scene.pairs > impl.max_pairs:
                reason = f"skipped: {scene.pairs:.1e} pairs"
            if reason is None:
                runnable.append(impl)
            else:
                skipped[impl.name] = reason
        for threads in args.threads:
            timings = benchmark_cell(runnable, scene, threads, args.repeats)
            medians = {name: t.medians_ms() for name, t in timings.items()}
            for impl in impls:
                if impl.name in skipped:
                    print(f"| {label} | {threads} | {impl.name} | - | - | - | - | {skipped[impl.name]} |")
                    continue
                f_ms, b_ms, fc_ms, bc_ms = medians[impl.name]
                print(f"| {label} | {threads} | {impl.name} | {f_ms:.1f} | {b_ms:.1f} | {fc_ms:.1f} | "
                      f"{bc_ms:.1f} | {_speedup(medians, skipped, impl.name)} |", flush=True)
    print(f"\nload average at end: {load_average('/')} (1/5/15 min)")


if __name__ == "__main__":
    main()
