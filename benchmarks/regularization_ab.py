"""HexPlane regularisers, torch Function against the compiled kernel, interleaved in ONE process: median ms.

    python benchmarks/regularization_ab.py [--repeats 9] [--threads 1] [--steps 0] -- -s /work/realdata/davis_libby \
        -r 1 --eval --coarse_iterations 0 [--plugin reflow]

A trainer is prepared as benchmarks/profile_step.py does (its model built from the arguments, no
step run), and its HexPlane's planes (views of one shared table, as in training) are regularised
with the trainer's weights, forward + backward into .grad, by the torch Function
(``REFLOW4DGS_REG_KERNEL=0``) and by the kernel alternately, `--repeats` times each (after one
untimed call each: the library's load). Also the same on contiguous copies of the planes. Prints
the medians (wall time and the thread's CPU time), their ratio and the largest differences of
value and gradient. With `--steps N`, then whole fine iterations (profile_step's, densification
off), blocks of N per engine, the order alternating, `--repeats` blocks each (the 2-core machine
is shared: interleaving slows both alike). Asserts nothing.
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

ENGINES = {"torch": "0", "kernel": "1"}


def _run(levels, weights, engine: str) -> tuple[float, float, float, list]:
    """(wall seconds, CPU seconds of this thread, value, grads) of one forward + backward by `engine`
    (grads cleared first). With one thread all the work runs on this thread, so its CPU time is
    what a busy machine distorts least."""
    from baselines.fourdgs import regularization, regularization_kernel

    os.environ[regularization_kernel.ENV_SWITCH] = ENGINES[engine]
    planes = [p for level in levels for p in level]
    for p in planes:
        p.grad = None
    start, cpu_start = time.perf_counter(), time.thread_time()
    total = regularization.hexplane_regularization(levels, *weights)
    total.backward()
    seconds, cpu_seconds = time.perf_counter() - start, time.thread_time() - cpu_start
    return seconds, cpu_seconds, float(total.detach()), [p.grad for p in planes]


def compare(levels, weights, repeats: int) -> dict[str, float]:
    """Median ms per engine, interleaved (order alternating), and the largest differences."""
    times: dict[str, list[float]] = {name: [] for name in ENGINES}
    cpu: dict[str, list[float]] = {name: [] for name in ENGINES}
    results = {}
    for name in ENGINES:  # the library's load, not timed
        results[name] = _run(levels, weights, name)
    for r in range(repeats):
        for name in (list(ENGINES) if r % 2 == 0 else list(ENGINES)[::-1]):
            seconds, cpu_seconds, _, _ = _run(levels, weights, name)
            times[name].append(seconds * 1e3)
            cpu[name].append(cpu_seconds * 1e3)
    (_, _, value_t, grads_t), (_, _, value_k, grads_k) = results["torch"], results["kernel"]
    grad_diff = max(((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()
                    for a, b in zip(grads_k, grads_t) if a is not None and b is not None)
    return {**{name: statistics.median(v) for name, v in times.items()},
            **{f"{name}_cpu": statistics.median(v) for name, v in cpu.items()},
            "value_rel": abs(value_k - value_t) / max(abs(value_t), 1e-30), "grad_rel": grad_diff}


def interleaved_steps(trainer, steps: int, rounds: int) -> dict[str, float]:
    """Median ms per whole training iteration with each engine (wall, and this thread's CPU time as
    `<engine>_cpu`), blocks of `steps`, order alternating."""
    from baselines.fourdgs import regularization_kernel
    from benchmarks.profile_step import _step

    times: dict[str, list[float]] = {name: [] for name in ENGINES}
    cpu: dict[str, list[float]] = {name: [] for name in ENGINES}
    for r in range(rounds):
        for name in (list(ENGINES) if r % 2 == 0 else list(ENGINES)[::-1]):
            os.environ[regularization_kernel.ENV_SWITCH] = ENGINES[name]
            _step(trainer, 1)  # the switch's first iteration is not timed
            for _ in range(steps):
                start, cpu_start = time.perf_counter(), time.thread_time()
                _step(trainer, 1)
                times[name].append((time.perf_counter() - start) * 1e3)
                cpu[name].append((time.thread_time() - cpu_start) * 1e3)
    return {**{name: statistics.median(v) for name, v in times.items()},
            **{f"{name}_cpu": statistics.median(v) for name, v in cpu.items()}}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, train_argv = split_passthrough(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9, help="timed calls per engine")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the kernel uses as many)")
    parser.add_argument("--steps", type=int, default=0,
                        help="also whole training iterations, blocks of this many per engine (0: none)")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.threads < 1 or args.steps < 0:
        parser.error("--repeats and --threads must be >= 1, --steps >= 0")
    apply_thread_policy()  # training's allocator policy (no chunk mmaps: few page faults) and OpenMP settings

    import torch

    from benchmarks.profile_step import _prepare

    saved = os.environ.get("REFLOW4DGS_REG_KERNEL")
    trainer = _prepare(train_argv, None, 0)
    torch.set_num_threads(args.threads)
    grid = trainer.ctx.model.deformation.deformation_net.grid
    hidden = trainer.hidden
    weights = (hidden.time_smoothness_weight, hidden.l1_time_planes, hidden.plane_tv_weight)
    levels = [list(level) for level in grid.grids]
    values = sum(p.numel() for level in levels for p in level)
    print(f"# regularization_ab: {args.threads} thread(s), {cpu_model()}, load {load_average()}")
    print(f"# {sum(len(level) for level in levels)} planes, {values} values ({values * levels[0][0].element_size() / 1e6:.1f} MB), "
          f"weights time_smoothness {weights[0]}, l1_time_planes {weights[1]}, plane_tv {weights[2]}")
    print("| planes | torch ms | kernel ms | kernel / torch | torch CPU ms | kernel CPU ms | value rel. diff | "
          "gradient rel. diff |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    copies = [[p.detach().contiguous().requires_grad_(True) for p in level] for level in levels]
    try:
        for label, planes in (("views of the shared table", levels), ("contiguous copies", copies)):
            m = compare(planes, weights, args.repeats)
            print(f"| {label} | {m['torch']:.1f} | {m['kernel']:.1f} | {m['kernel'] / m['torch']:.2f}x | "
                  f"{m['torch_cpu']:.1f} | {m['kernel_cpu']:.1f} | {m['value_rel']:.1e} | {m['grad_rel']:.1e} |",
                  flush=True)
        del copies
        if args.steps:
            for level in levels:
                for p in level:
                    p.grad = None
            print(f"# whole iterations ({trainer.ctx.model.num_gaussians} Gaussians), load {load_average()}")
            m = interleaved_steps(trainer, args.steps, args.repeats)
            print("| whole iteration | torch ms | kernel ms | kernel / torch | torch CPU ms | kernel CPU ms | "
                  "kernel / torch (CPU) |\n|---|---:|---:|---:|---:|---:|---:|")
            print(f"| median of {args.steps * args.repeats} | {m['torch']:.1f} | {m['kernel']:.1f} | "
                  f"{m['kernel'] / m['torch']:.2f}x | {m['torch_cpu']:.1f} | {m['kernel_cpu']:.1f} | "
                  f"{m['kernel_cpu'] / m['torch_cpu']:.2f}x |", flush=True)
    finally:
        if saved is None:
            os.environ.pop("REFLOW4DGS_REG_KERNEL", None)
        else:
            os.environ["REFLOW4DGS_REG_KERNEL"] = saved
    print(f"# load at the end {load_average()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
