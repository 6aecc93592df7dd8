"""Speed of the compiled CPU compositor against torch compositors; prints a markdown table.

    python benchmarks/raster_kernel.py                     # default sizes, 1 and 2 threads
    python benchmarks/raster_kernel.py --sizes 20000x256x256 --threads 2 --repeats 9

Times the COMPOSITING stage (what the kernel replaces; tile binning included) on one shared
projection: forward, and forward + backward of a random linear loss on image and alpha down to
means2d, conics, opacities and features. Medians over --repeats runs, in milliseconds; the ratio
columns are (other / kernel) for forward + backward. Columns:

- CPU: the kernel's forward + backward in process CPU time summed over threads; on a machine
  shared with other work it shows the kernel's own cost where wall time does not.

- kernel: baselines.render.kernel.composite_kernel (C++).
- torch tiled: baselines.render.composite_tiled.composite_tiled when that module is present,
  else "n/a".
- per-tile torch: a plain loop over tiles applying the reference's dense formula to each
  tile's depth-sorted list (a minimal torch tiled renderer, for scale; autograd backward);
  only where pixels x Gaussians stays below --per-tile-limit.
- reference: the dense oracle, only where pixels x Gaussians stays below --dense-limit.
- rasterize: the whole `rasterize(backend="cpu")` forward + backward (projection included) down
  to means, quats, scales, opacities and features.

Scenes are realistic for training: N Gaussians spread over the view at depths 2 to 6, each about
2 pixels (standard deviation) wide on screen, opacities uniform in [0.05, 0.95], C = 3 features
(the API adds depth as a 4th channel; so does this script). `--compile` also times a cold build
of the kernel into a temporary cache. The machine's load average is printed: other processes
on the same cores inflate every figure.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from baselines.render import kernel  # noqa: E402
from baselines.render.composite_reference import composite_pixels, composite_reference, pixel_centres  # noqa: E402
from baselines.render.projection import Projection, project_gaussians_torch  # noqa: E402
from baselines.render.tiles import bin_gaussians  # noqa: E402
from baselines.render import rasterize  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "features")
Compositor = Callable[[Projection, torch.Tensor, torch.Tensor, int, int], "tuple[torch.Tensor, torch.Tensor]"]


def make_scene(n: int, width: int, height: int, channels: int = 3, seed: int = 0) -> dict:
    """rasterize() keyword arguments for N Gaussians about 2 px wide, in front of the camera."""
    g = torch.Generator().manual_seed(seed)
    focal = float(max(width, height))
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) - 0.5) * 1.1 * z * width / focal
    y = (torch.rand(n, generator=g) - 0.5) * 1.1 * z * height / focal
    return {
        "means": torch.stack([x, y, z], dim=1),
        "quats": torch.randn(n, 4, generator=g),
        "scales": (0.4 + 0.8 * torch.rand(n, 3, generator=g)) * 2.0 * z[:, None] / focal,
        "opacities": 0.05 + 0.9 * torch.rand(n, generator=g),
        "features": torch.rand(n, channels, generator=g),
        "viewmat": torch.eye(4),
        "K": torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]]),
        "width": width,
        "height": height,
    }


def per_tile_torch(projection: Projection, opacities: torch.Tensor, features: torch.Tensor, width: int, height: int):
    """Minimal torch tiled compositor: the reference formula on each tile's sorted list."""
    bins = bin_gaussians(projection, width, height)
    ts = bins.tile_size
    centres = pixel_centres(width, height, features.dtype, features.device).reshape(height, width, 2)
    image = features.new_zeros(height, width, features.shape[1])
    alpha = features.new_zeros(height, width, 1)
    offsets = bins.offsets.tolist()
    for tile in range(bins.tiles_x * bins.tiles_y):
        ids = bins.gaussian_ids[offsets[tile]:offsets[tile + 1]]
        if ids.numel() == 0:
            continue
        ty, tx = divmod(tile, bins.tiles_x)
        pix = centres[ty * ts:(ty + 1) * ts, tx * ts:(tx + 1) * ts]
        h, w = pix.shape[:2]
        f, a = composite_pixels(pix.reshape(-1, 2), projection.means2d[ids], projection.conics[ids], opacities[ids],
                                features[ids])
        image[ty * ts:ty * ts + h, tx * ts:tx * ts + w] = f.reshape(h, w, -1)
        alpha[ty * ts:ty * ts + h, tx * ts:tx * ts + w] = a.reshape(h, w, 1)
    return image, alpha


def torch_tiled() -> Compositor | None:
    try:
        from baselines.render.composite_tiled import composite_tiled
    except ImportError:
        return None
    return composite_tiled


def time_compositor(fn: Compositor, scene: dict, repeats: int) -> tuple[float, float, float]:
    """(forward ms, forward + backward ms, forward + backward CPU ms of all threads), medians."""
    leaves = {k: scene[k].clone().requires_grad_(True) for k in PARAMS}
    proj = project_gaussians_torch(leaves["means"], leaves["quats"], leaves["scales"], scene["viewmat"], scene["K"],
                                   scene["width"], scene["height"], leaves["opacities"])
    depth = proj.depths.detach().unsqueeze(1)
    feats = torch.cat([leaves["features"].detach(), depth], dim=1).requires_grad_(True)
    means2d = proj.means2d.detach().requires_grad_(True)
    conics = proj.conics.detach().requires_grad_(True)
    opac = leaves["opacities"].detach().requires_grad_(True)
    p = Projection(means2d=means2d, cov2d=proj.cov2d.detach(), conics=conics, depths=proj.depths.detach(),
                   radii=proj.radii, visible=proj.visible)
    w, h = scene["width"], scene["height"]
    g = torch.Generator().manual_seed(1)
    gi = torch.randn(h, w, feats.shape[1], generator=g)
    ga = torch.randn(h, w, 1, generator=g)
    fwd, both, cpu = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        with torch.no_grad():
            fn(p, opac, feats, w, h)
        t1 = time.perf_counter()
        c1 = time.process_time()
        image, alpha = fn(p, opac, feats, w, h)
        torch.autograd.grad((image * gi).sum() + (alpha * ga).sum(), (means2d, conics, opac, feats))
        t2 = time.perf_counter()
        cpu.append(time.process_time() - c1)
        fwd.append(t1 - t0)
        both.append(t2 - t1)
    return 1e3 * statistics.median(fwd), 1e3 * statistics.median(both), 1e3 * statistics.median(cpu)


def time_rasterize(scene: dict, repeats: int) -> float:
    """Median ms of rasterize(backend="cpu") forward + backward to the 3D parameters."""
    runs = []
    for _ in range(repeats):
        leaves = {k: scene[k].clone().requires_grad_(True) for k in PARAMS}
        t0 = time.perf_counter()
        feats, depth, alpha, _ = rasterize(**{**scene, **leaves}, backend="cpu")
        (feats.sum() + depth.sum() + alpha.sum()).backward()
        runs.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(runs)


def time_cold_build() -> float:
    compiler = kernel.find_compiler()
    if compiler is None:
        return float("nan")
    with tempfile.TemporaryDirectory() as tmp:
        old = os.environ.get(kernel.ENV_CACHE_DIR)
        os.environ[kernel.ENV_CACHE_DIR] = tmp
        try:
            target = kernel.library_path(compiler)
            t0 = time.perf_counter()
            kernel._build(compiler, target)
            return time.perf_counter() - t0
        finally:
            if old is None:
                del os.environ[kernel.ENV_CACHE_DIR]
            else:
                os.environ[kernel.ENV_CACHE_DIR] = old


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _fmt(ms: float | None) -> str:
    return "n/a" if ms is None else f"{ms:.1f}"


def _ratio(other: float | None, base: float) -> str:
    return "n/a" if other is None else f"{other / base:.1f}x"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="2000x128x128,20000x256x256,100000x512x512",
                        help="comma-separated NxWIDTHxHEIGHT")
    parser.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per entry (median reported)")
    parser.add_argument("--torch-repeats", type=int, default=3, help="timed runs for the torch compositors")
    parser.add_argument("--dense-limit", type=float, default=5e7, help="max pixels x Gaussians for the reference")
    parser.add_argument("--per-tile-limit", type=float, default=2e9,
                        help="max pixels x Gaussians for the per-tile torch column (0 skips it)")
    parser.add_argument("--compile", action="store_true", help="also time a cold build of the kernel")
    args = parser.parse_args(argv)

    ok, reason = kernel.kernel_available()
    if not ok:
        raise SystemExit(f"compiled kernel unavailable: {reason}")
    tiled = torch_tiled()
    print(f"machine: {_cpu_name()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"load average at start {os.getloadavg()[0]:.2f}")
    if args.compile:
        print(f"cold kernel build: {time_cold_build():.2f} s")
    header = ("| N | image | threads | kernel fwd | kernel fwd+bwd | kernel fwd+bwd CPU | torch tiled fwd+bwd | ratio "
              "| per-tile torch fwd+bwd | ratio | reference fwd+bwd | ratio | rasterize fwd+bwd (cpu) |")
    print()
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for spec in args.sizes.split(","):
        n, width, height = (int(v) for v in spec.lower().split("x"))
        scene = make_scene(n, width, height)
        for threads in (int(t) for t in args.threads.split(",")):
            torch.set_num_threads(threads)
            kfn = lambda p, o, f, w, h, t=threads: kernel.composite_kernel(p, o, f, w, h, num_threads=t)  # noqa: E731
            time_compositor(kfn, scene, 1)  # warm-up
            k_fwd, k_both, k_cpu = time_compositor(kfn, scene, args.repeats)
            t_both = time_compositor(tiled, scene, args.torch_repeats)[1] if tiled else None
            p_both = None
            if n * width * height <= args.per_tile_limit:
                p_both = time_compositor(per_tile_torch, scene, args.torch_repeats)[1]
            r_both = None
            if n * width * height <= args.dense_limit:
                r_both = time_compositor(composite_reference, scene, args.torch_repeats)[1]
            full = time_rasterize(scene, args.repeats)
            print(f"| {n} | {width}x{height} | {threads} | {_fmt(k_fwd)} | {_fmt(k_both)} | {_fmt(k_cpu)} | "
                  f"{_fmt(t_both)} | {_ratio(t_both, k_both)} | {_fmt(p_both)} | {_ratio(p_both, k_both)} | "
                  f"{_fmt(r_both)} | {_ratio(r_both, k_both)} | {_fmt(full)} |", flush=True)
    print(f"\nload average at end {os.getloadavg()[0]:.2f}; times in ms (median); CPU = process CPU time of "
          "all threads (less sensitive to other load than wall time)")


if __name__ == "__main__":
    main()
