"""Compiled SSIM map against its torch twin, interleaved in ONE process: median ms of forward + backward.

    python benchmarks/ssim_ab.py [--reps 5] [--rounds 4] [--threads 1] [--dtype float32]

For each shape ([8, 180, 320, 3]: the flow-matching loss's batched photometric terms at 320x180;
[2, 480, 854, 3]: the host's D-SSIM on two 480p views) the two variants run in blocks of `--reps`
calls, their order alternating round by round, so a busy machine (the 2-core machine is shared)
slows both alike. One call is `ssim_map(img, gt)` with img requiring grad, then `backward` of a
random weighting of the map (gt constant, as in training). Also prints the largest difference of
the maps and of the image gradients. Asserts nothing.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402

from baselines import ssim_kernel  # noqa: E402
from baselines.metrics import ssim_map, ssim_map_torch  # noqa: E402
from benchmarks.machine import cpu_model, load_average  # noqa: E402

SHAPES = ((8, 180, 320, 3), (2, 480, 854, 3))
VARIANTS = {"torch": ssim_map_torch, "kernel": ssim_map}


def _call(fn, img: torch.Tensor, gt: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    x = img.detach().requires_grad_()
    out = fn(x, gt)
    (out * weights).sum().backward()
    return out.detach(), x.grad


def interleaved(img: torch.Tensor, gt: torch.Tensor, reps: int, rounds: int) -> dict[str, float]:
    """Median ms of one forward + backward per variant, blocks of `reps` calls, order alternating by round."""
    weights = torch.randn(img.shape, generator=torch.Generator().manual_seed(1), dtype=img.dtype)
    times: dict[str, list[float]] = {name: [] for name in VARIANTS}
    names = list(VARIANTS)
    for r in range(rounds):
        for name in (names if r % 2 == 0 else names[::-1]):
            _call(VARIANTS[name], img, gt, weights)  # the block's first call is not timed
            for _ in range(reps):
                start = time.perf_counter()
                _call(VARIANTS[name], img, gt, weights)
                times[name].append((time.perf_counter() - start) * 1e3)
    return {name: statistics.median(v) for name, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=5, help="timed calls per block")
    parser.add_argument("--rounds", type=int, default=4, help="blocks per variant")
    parser.add_argument("--threads", type=int, default=1, help="torch and kernel threads (training uses 1)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    args = parser.parse_args(argv)
    if args.reps < 1 or args.rounds < 1 or args.threads < 1:
        parser.error("--reps, --rounds and --threads must be >= 1")
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    gen = torch.Generator().manual_seed(0)
    probe = torch.zeros(1, 1, 1, 1, dtype=dtype)
    reason = ssim_kernel.unusable_reason(probe, probe)
    if reason is not None:
        print(f"ssim_ab: the compiled SSIM cannot run: {reason}", file=sys.stderr)
        return 2
    print(f"# ssim_ab: {args.threads} thread(s), {args.dtype}, {cpu_model()}, load {load_average()}")
    print("| shape | torch ms | kernel ms | torch / kernel | max map diff | max grad diff / max grad |")
    print("|---|---:|---:|---:|---:|---:|")
    for shape in SHAPES:
        gt = torch.rand(shape, generator=gen, dtype=dtype)
        img = (gt + 0.1 * torch.randn(shape, generator=gen, dtype=dtype)).clamp(0, 1)
        weights = torch.randn(shape, generator=gen, dtype=dtype)
        (map_t, grad_t), (map_k, grad_k) = (_call(fn, img, gt, weights) for fn in VARIANTS.values())
        map_diff = (map_t - map_k).abs().max().item()
        grad_diff = ((grad_t - grad_k).abs().max() / grad_t.abs().max()).item()
        medians = interleaved(img, gt, args.reps, args.rounds)
        print(f"| {list(shape)} | {medians['torch']:.1f} | {medians['kernel']:.1f} | "
              f"{medians['torch'] / medians['kernel']:.2f}x | {map_diff:.1e} | {grad_diff:.1e} |", flush=True)
    print(f"# load at the end {load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
