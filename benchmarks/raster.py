"""Rasterizer speed: forward and forward+backward median milliseconds per implementation.

    python benchmarks/raster.py [--threads 2] [--repeats 5] [--sizes 2000x128x128,20000x256x256]

Scenes look like a trained model seen from a training camera: Gaussians spread over the view
frustum at depths 2..8, each a few pixels on screen (screen-space standard deviation
log-uniform in [0.5, 3] px, anisotropic, random rotation), opacities uniform in [0.05, 0.95],
RGB features. "forward" is the training forward (inputs require grad); "fwd+bwd" adds the
backward of a weighted sum of image, depth and alpha. Every implementation renders the same
scene; the speed-up column is reference time / implementation time from the same run.

To benchmark a new implementation, add one entry to IMPLEMENTATIONS.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from baselines.render import rasterize  # noqa: E402
from baselines.render.api import _composite  # noqa: E402
from baselines.render.backends import Backend, gsplat_unavailable_reason  # noqa: E402
from baselines.render.composite_tiled import composite_tiled  # noqa: E402
from baselines.render.projection import project_gaussians_torch  # noqa: E402

DEFAULT_SIZES = "2000x128x128,20000x256x256,100000x512x512"
REFERENCE_MAX_PAIRS = 5e7  # pixel x Gaussian pairs beyond which the dense reference takes minutes


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

    def to(self, device: str) -> "Scene":
        return Scene(*(getattr(self, f).to(device) for f in ("means", "quats", "scales", "opacities", "features",
                                                             "viewmat", "K")), self.width, self.height)


def make_scene(n: int, width: int, height: int, seed: int = 0) -> Scene:
    g = torch.Generator().manual_seed(seed)
    f = float(width)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    z = torch.empty(n).uniform_(2.0, 8.0, generator=g)
    u = torch.empty(n).uniform_(-0.1 * width, 1.1 * width, generator=g)
    v = torch.empty(n).uniform_(-0.1 * height, 1.1 * height, generator=g)
    means = torch.stack([(u - K[0, 2]) / f * z, (v - K[1, 2]) / f * z, z], dim=-1)
    sigma_px = torch.exp(torch.empty(n, 1).uniform_(math.log(0.5), math.log(3.0), generator=g))
    aniso = torch.exp(torch.empty(n, 3).uniform_(-0.7, 0.7, generator=g))
    return Scene(means, torch.randn(n, 4, generator=g), sigma_px * aniso * z[:, None] / f,
                 torch.empty(n).uniform_(0.05, 0.95, generator=g), torch.rand(n, 3, generator=g),
                 torch.eye(4), K, width, height)


@dataclass
class Implementation:
    """One row group of the table: how to render a scene, and whether it can run here."""

    name: str
    render: Callable[[Scene], tuple[torch.Tensor, ...]]  # -> (image, depth, alpha)
    device: str = "cpu"
    unavailable: Callable[[], str | None] = lambda: None
    max_pairs: float = math.inf  # skip scenes with more pixel x Gaussian pairs (would take minutes)


def from_backend(name: str, backend: str, device: str = "cpu", **kwargs) -> Implementation:
    def render(s: Scene):
        return rasterize(s.means, s.quats, s.scales, s.opacities, s.features, s.viewmat, s.K, s.width, s.height,
                         backend=backend)[:3]
    return Implementation(name, render, device, **kwargs)


def from_compositor(name: str, compositor, **kwargs) -> Implementation:
    """A compositing function with the backend signature, after the shared torch projection."""
    stage = Backend(name, project_gaussians_torch, compositor)

    def render(s: Scene):
        proj = project_gaussians_torch(s.means, s.quats, s.scales, s.viewmat, s.K, s.width, s.height, s.opacities)
        return _composite(stage, proj, s.opacities, s.features, s.width, s.height, None)
    return Implementation(name, render, **kwargs)


IMPLEMENTATIONS: list[Implementation] = [
    from_backend("reference", "reference", max_pairs=REFERENCE_MAX_PAIRS),
    from_backend("cpu", "cpu"),
    from_compositor("torch_tiled", composite_tiled),
    from_backend("gsplat", "gsplat", device="cuda",
                 unavailable=lambda: gsplat_unavailable_reason(torch.device("cuda"))),
]


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_implementation(impl: Implementation, scene: Scene, repeats: int) -> tuple[float, float]:
    """Median (forward ms, forward+backward ms) after one warm-up run."""
    scene = scene.to(impl.device)
    leaves = [scene.means, scene.quats, scene.scales, scene.opacities, scene.features]
    weights = None
    fwd, both = [], []
    for run in range(repeats + 1):
        for t in leaves:
            t.requires_grad_(True)
            t.grad = None
        _sync(impl.device)
        start = time.perf_counter()
        outputs = impl.render(scene)
        _sync(impl.device)
        middle = time.perf_counter()
        if weights is None:
            g = torch.Generator().manual_seed(1)
            weights = [torch.randn(o.shape, generator=g).to(impl.device) for o in outputs]
        sum((o * w).sum() for o, w in zip(outputs, weights)).backward()
        _sync(impl.device)
        end = time.perf_counter()
        if run:  # the first run warms caches and lazy initialisation
            fwd.append(middle - start)
            both.append(end - start)
    return 1e3 * statistics.median(fwd), 1e3 * statistics.median(both)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch intra-op threads")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per cell (median reported)")
    parser.add_argument("--sizes", default=DEFAULT_SIZES, help="comma-separated NxWxH scenes")
    parser.add_argument("--only", default="", help="comma-separated implementation names (default: all)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    wanted = {name for name in args.only.split(",") if name}
    impls = [i for i in IMPLEMENTATIONS if not wanted or i.name in wanted]

    print(f"torch {torch.__version__}, {args.threads} thread(s), median of {args.repeats} runs\n")
    print("| scene | implementation | forward ms | fwd+bwd ms | speed-up vs reference (fwd / fwd+bwd) |")
    print("|---|---|---:|---:|---|")
    for size in args.sizes.split(","):
        n, w, h = (int(v) for v in size.lower().split("x"))
        scene = make_scene(n, w, h)
        label = f"{n // 1000}k, {w}x{h}" if n >= 1000 else f"{n}, {w}x{h}"
        reference_ms = None
        for impl in impls:
            reason = impl.unavailable()
            if reason is None and n * w * h > impl.max_pairs:
                reason = f"skipped: {n * w * h:.1e} pixel x Gaussian pairs would take minutes"
            if reason is not None:
                print(f"| {label} | {impl.name} | - | - | {reason} |")
                continue
            f_ms, b_ms = time_implementation(impl, scene, args.repeats)
            if impl.name == "reference":
                reference_ms = (f_ms, b_ms)
                ratio = "1.0 / 1.0"
            elif reference_ms is None:
                ratio = "n/a (no reference in this run)"
            else:
                ratio = f"{reference_ms[0] / f_ms:.1f} / {reference_ms[1] / b_ms:.1f}"
            print(f"| {label} | {impl.name} | {f_ms:.1f} | {b_ms:.1f} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
