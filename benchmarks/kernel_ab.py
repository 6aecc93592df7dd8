"""Compiled CPU kernels against their torch twins, interleaved in ONE process: median ms per iteration.

    python benchmarks/kernel_ab.py [--iters 4] [--rounds 4] [--baseline] -- -s data/real/nvidia_balloon1 -r 4 \
        --eval --coarse_iterations 0 --plugin reflow --configs arguments/nvidia/reflow.py

A trainer is prepared as benchmarks/profile_step.py does (fine stage, densification off, `--warmup 0`),
then fine iterations run in blocks of `--iters`, one block per variant, the variants' order
alternating round by round, so a busy machine (the 2-core machine is shared) slows every variant
alike. The variants switch kernels by their environment switches, which are read at each call:

    torch      REFLOW4DGS_PROJECT_KERNEL=0, REFLOW4DGS_FLOW_KERNEL=0, REFLOW4DGS_SSIM_KERNEL=0 (the torch twins)
    project    the compiled projection (baselines/render/project_kernel.py) alone
    project+flow   and ReFlow's compiled flow channels (reflow_plugin/flow_kernel.py)
    project+flow+ssim  and the compiled SSIM map (baselines/ssim_kernel.py)

`--baseline` also measures the same arguments without the plugin (profile_step.baseline_argv) at
the plugin run's Gaussian count. Prints the medians and the ratios to `torch`; asserts nothing.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(0, str(REPO_ROOT))

from benchmarks.cli import split_passthrough  # noqa: E402
from benchmarks.machine import cpu_model, load_average  # noqa: E402

from baselines.thread_policy import apply_thread_policy  # noqa: E402

VARIANTS = {
    "torch": {"REFLOW4DGS_PROJECT_KERNEL": "0", "REFLOW4DGS_FLOW_KERNEL": "0", "REFLOW4DGS_SSIM_KERNEL": "0"},
    "project": {"REFLOW4DGS_PROJECT_KERNEL": "1", "REFLOW4DGS_FLOW_KERNEL": "0", "REFLOW4DGS_SSIM_KERNEL": "0"},
    "project+flow": {"REFLOW4DGS_PROJECT_KERNEL": "1", "REFLOW4DGS_FLOW_KERNEL": "1", "REFLOW4DGS_SSIM_KERNEL": "0"},
    "project+flow+ssim": {"REFLOW4DGS_PROJECT_KERNEL": "1", "REFLOW4DGS_FLOW_KERNEL": "1",
                          "REFLOW4DGS_SSIM_KERNEL": "1"},
}


def interleaved(trainer, iters: int, rounds: int) -> dict[str, float]:
    """Median ms per iteration of each variant, blocks of `iters` iterations, order alternating by round."""
    from benchmarks.profile_step import _step

    times: dict[str, list[float]] = {name: [] for name in VARIANTS}
    names = list(VARIANTS)
    saved = {key: os.environ.get(key) for env in VARIANTS.values() for key in env}
    try:
        for r in range(rounds):
            for name in (names if r % 2 == 0 else names[::-1]):
                os.environ.update(VARIANTS[name])
                _step(trainer, 1)  # the switch's first iteration (a library load) is not timed
                for _ in range(iters):
                    start = time.perf_counter()
                    _step(trainer, 1)
                    times[name].append((time.perf_counter() - start) * 1e3)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
    return {name: statistics.median(v) for name, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, train_argv = split_passthrough(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iters", type=int, default=4, help="timed iterations per block")
    parser.add_argument("--rounds", type=int, default=4, help="blocks per variant")
    parser.add_argument("--baseline", action="store_true", help="also the arguments without the plugin")
    args = parser.parse_args(argv)
    if args.iters < 1 or args.rounds < 1:
        parser.error("--iters and --rounds must be >= 1")
    policy = apply_thread_policy() or "thread policy: user's"

    from benchmarks.profile_step import _prepare, _step, baseline_argv

    print(f"# kernel_ab: {policy}, {cpu_model()}, load {load_average()}")
    runs = [("as given", train_argv, None)]
    if args.baseline:
        runs.append(("without the plugin", baseline_argv(train_argv), None))
    count = None
    print("| arguments | Gaussians | " + " | ".join(f"{n} ms" for n in VARIANTS) + " | " +
          " | ".join(f"{n} / torch" for n in list(VARIANTS)[1:]) + " |")
    print("|---|---:|" + "---:|" * (2 * len(VARIANTS) - 1))
    for label, targv, _ in runs:
        trainer = _prepare(targv, None, 0, count)
        _step(trainer, 3)  # allocator and caches warm
        count = trainer.ctx.model.num_gaussians
        medians = interleaved(trainer, args.iters, args.rounds)
        base = medians["torch"]
        print(f"| {label} | {count} | " + " | ".join(f"{medians[n]:.1f}" for n in VARIANTS) + " | " +
              " | ".join(f"{medians[n] / base:.2f}x" for n in list(VARIANTS)[1:]) + " |", flush=True)
    print(f"# load at the end {load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
