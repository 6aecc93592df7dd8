"""Count the compositing kernel's work on a benchmark scene: the input of a roofline estimate.

    python benchmarks/raster_work.py                      # 20k Gaussians, 256x256 (benchmarks/raster.py's scene)
    python benchmarks/raster_work.py --size 100000x512x512

The compiled kernel (baselines/render/csrc/raster_kernel.cpp) visits, for every (tile, Gaussian)
intersection and every row of the Gaussian's box inside the tile, only the columns where
sigma <= ln(255 o) can hold, in chunks of 8 pixels (one AVX2 vector of float32). This script
replays that geometry in numpy (the same ellipse spans, plus the kernel's one-pixel slack per
side; the kernel's extra rounding margin is below a pixel and ignored) and prints:

- tile pairs: tile pixels x list length (the work of a tile loop without spans);
- chunks: 8-lane vectors the kernel evaluates in phase A (sigma, exp, alpha) when no pixel stops
  early, and the lanes in them that lie inside the spans;
- contributions: (pixel, Gaussian) pairs with alpha >= 1/255 in front-to-back order up to each
  pixel's transmittance stop (T < 1e-4), i.e. the pairs phase B composites.

docs/RASTERIZER.md ("Roofline") turns these counts and the measured kernel time into cycles per
chunk and compares them with the instructions a chunk needs.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(0, str(REPO_ROOT))
    sys.path.insert(0, str(Path(__file__).resolve().parent))

LANES = 8
ALPHA_MIN, ALPHA_MAX, T_MIN = 1.0 / 255.0, 0.999, 1e-4


def count_work(n: int, width: int, height: int, kind: str = "trained") -> dict[str, float]:
    import torch

    from baselines.render.projection import project_gaussians_torch
    from baselines.render.tiles import bin_gaussians
    from raster import make_scene  # benchmarks/raster.py, beside this script

    scene = make_scene(n, width, height, kind=kind)
    with torch.no_grad():
        proj = project_gaussians_torch(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K,
                                       width, height, opacities=scene.opacities)
        bins = bin_gaussians(proj, width, height)
    mx, my = proj.means2d[:, 0].double().numpy(), proj.means2d[:, 1].double().numpy()
    a, b, c = (proj.conics[:, i].double().numpy() for i in range(3))
    opacity = scene.opacities.double().numpy()
    cut = np.log(255.0 * np.maximum(opacity, 1e-12))
    offsets, ids = bins.offsets.numpy(), bins.gaussian_ids.numpy()
    ts = bins.tile_size
    tile_pairs = chunks = span_lanes = contributions = 0
    for tile in range(bins.tiles_x * bins.tiles_y):
        g = ids[offsets[tile]:offsets[tile + 1]]
        if g.size == 0:
            continue
        x0, y0 = (tile % bins.tiles_x) * ts, (tile // bins.tiles_x) * ts
        x1, y1 = min(x0 + ts, width), min(y0 + ts, height)
        tile_pairs += g.size * (x1 - x0) * (y1 - y0)
        rows = np.arange(y0, y1) + 0.5
        dy = rows[None, :] - my[g, None]                                       # [G, rows]
        disc = 2 * a[g, None] * cut[g, None] - dy**2 * (a[g, None] * c[g, None] - b[g, None] ** 2)
        half = np.sqrt(np.maximum(disc, 0)) / a[g, None]
        centre = mx[g, None] - b[g, None] / a[g, None] * dy
        lo = np.maximum(np.ceil(centre - half - 0.5) - 1, x0)                  # pixel j centre = j + 0.5
        hi = np.minimum(np.floor(centre + half - 0.5) + 1, x1 - 1)
        ok = (disc >= 0) & (hi >= lo)
        span = np.where(ok, hi - lo + 1, 0)
        span_lanes += span.sum()
        # chunks start at the span's first column, every 8 columns (the kernel shifts the last
        # chunk of a row left so it stays inside the tile; the count is the same)
        chunks += np.where(ok, np.ceil(span / LANES), 0).sum()
        # pixel-exact compositing, front to back, to count what phase B composites
        px = np.arange(x0, x1) + 0.5
        dxs = px[None, None, :] - mx[g, None, None]                            # [G, 1, W]
        sigma = 0.5 * (a[g, None, None] * dxs**2 + c[g, None, None] * dy[:, :, None] ** 2) \
            + b[g, None, None] * dxs * dy[:, :, None]
        alpha = np.minimum(opacity[g, None, None] * np.exp(-sigma), ALPHA_MAX)
        alpha = np.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)
        T = np.cumprod(1.0 - alpha, axis=0)
        # composited: alpha passes and the transmittance after it stays above the stop (a pixel
        # whose T would fall below stops before that Gaussian; T only decreases)
        contributions += ((alpha > 0) & (T > T_MIN)).sum()
    return {"gaussians": n, "width": width, "height": height, "intersections": int(ids.size),
            "tile_pairs": int(tile_pairs), "chunks": int(chunks), "span_lanes": int(span_lanes),
            "contributions": int(contributions)}


def time_compositing(n: int, width: int, height: int, threads: int, repeats: int = 7) -> tuple[float, float]:
    """Median ms of the cpu backend's compositing alone (binning included), forward and fwd+bwd.

    The projection is computed once and its outputs are made leaves, so neither the torch
    projection nor its backward is timed (benchmarks/raster.py times the whole pipeline).
    """
    import statistics
    import time

    import torch

    from baselines.render.backends import resolve_backend
    from baselines.render.projection import project_gaussians_torch
    from raster import make_scene

    torch.set_num_threads(threads)
    scene = make_scene(n, width, height)
    backend = resolve_backend("cpu", torch.device("cpu"))
    with torch.no_grad():
        proj = project_gaussians_torch(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K,
                                       width, height, opacities=scene.opacities)
    for name in ("means2d", "conics", "depths"):
        setattr(proj, name, getattr(proj, name).detach().clone().requires_grad_(True))
    opacities = scene.opacities.detach().clone().requires_grad_(True)
    features = torch.cat([scene.features, proj.depths.detach()[:, None]], 1).requires_grad_(True)
    weights = torch.rand(height, width, features.shape[1], generator=torch.Generator().manual_seed(1))

    def forward():
        with torch.no_grad():
            backend.composite(proj, opacities, features, width, height)

    def forward_backward():
        image, _ = backend.composite(proj, opacities, features, width, height)
        (image * weights).sum().backward()

    medians = []
    for fn in (forward, forward_backward):
        fn()
        samples = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            samples.append(time.perf_counter() - start)
        medians.append(statistics.median(samples) * 1e3)
    return medians[0], medians[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="20000x256x256", help="NxWxH")
    args = parser.parse_args()
    n, w, h = (int(v) for v in args.size.split("x"))
    work = count_work(n, w, h)
    pixels = w * h
    print(f"# {n} Gaussians, {w}x{h} (benchmarks/raster.py's 'trained' scene)")
    for key in ("intersections", "tile_pairs", "chunks", "span_lanes", "contributions"):
        print(f"{key:14s} {work[key]:>12,d}   {work[key] / pixels:8.1f} per pixel")
    print(f"lanes used per chunk {work['span_lanes'] / max(1, work['chunks']):.2f} of {LANES}")
    for threads in (1, 2):
        fwd, both = time_compositing(n, w, h, threads)
        print(f"compositing alone (binning included), {threads} thread(s): forward {fwd:.1f} ms, "
              f"forward+backward {both:.1f} ms; forward {fwd * 1e6 / work['chunks']:.0f} ns per chunk, "
              f"{fwd * 1e6 / work['intersections']:.0f} ns per intersection")


if __name__ == "__main__":
    main()
