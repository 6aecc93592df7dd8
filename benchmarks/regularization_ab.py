"""HexPlane regularisers, torch Function against the compiled kernel, interleaved in ONE process: median ms.

    python benchmarks/regularization_ab.py [--repeats 9] [--threads 1] -- -s /work/realdata/davis_libby -r 1 \
        --eval --coarse_iterations 0

A trainer is prepared as benchmarks/profile_step.py does (its model built from the arguments, no
step run), and its HexPlane's planes (views of one shared table, as in training) are regularised
with the trainer's weights, forward + backward into .grad, by the torch Function
(``REFLOW4DGS_REG_KERNEL=0``) and by the kernel alternately, `--repeats` times each (after one
untimed call each: the library's load). Also the same on contiguous copies of the planes. Prints
the medians, their ratio and the largest differences of value and gradient; asserts nothing.
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

from benchmarks.machine import cpu_model, load_average  # noqa: E402

ENGINES = {"torch": "0", "kernel": "1"}


def _run(levels, weights, engine: str) -> tuple[float, float, list]:
    """(seconds, value, grads) of one forward + backward by `engine` (grads cleared first)."""
    from baselines.fourdgs import regularization, regularization_kernel

    os.environ[regularization_kernel.ENV_SWITCH] = ENGINES[engine]
    planes = [p for level in levels for p in level]
    for p in planes:
        p.grad = None
    start = time.perf_counter()
    total = regularization.hexplane_regularization(levels, *weights)
    total.backward()
    seconds = time.perf_counter() - start
    return seconds, float(total), [p.grad for p in planes]


def compare(levels, weights, repeats: int) -> dict[str, float]:
    """Median ms per engine, interleaved (order alternating), and the largest differences."""
    times: dict[str, list[float]] = {name: [] for name in ENGINES}
    results = {}
    for name in ENGINES:  # the library's load, not timed
        results[name] = _run(levels, weights, name)
    for r in range(repeats):
        for name in (list(ENGINES) if r % 2 == 0 else list(ENGINES)[::-1]):
            times[name].append(_run(levels, weights, name)[0] * 1e3)
    (_, value_t, grads_t), (_, value_k, grads_k) = results["torch"], results["kernel"]
    grad_diff = max(((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()
                    for a, b in zip(grads_k, grads_t) if a is not None and b is not None)
    return {**{name: statistics.median(v) for name, v in times.items()},
            "value_rel": abs(value_k - value_t) / max(abs(value_t), 1e-30), "grad_rel": grad_diff}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    train_argv: list[str] = []
    if "--" in argv:
        train_argv, argv = argv[argv.index("--") + 1:], argv[:argv.index("--")]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9, help="timed calls per engine")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the kernel uses as many)")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.threads < 1:
        parser.error("--repeats and --threads must be >= 1")

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
    print("| planes | torch ms | kernel ms | kernel / torch | value rel. diff | gradient rel. diff |")
    print("|---|---:|---:|---:|---:|---:|")
    copies = [[p.detach().contiguous().requires_grad_(True) for p in level] for level in levels]
    try:
        for label, planes in (("views of the shared table", levels), ("contiguous copies", copies)):
            m = compare(planes, weights, args.repeats)
            print(f"| {label} | {m['torch']:.1f} | {m['kernel']:.1f} | {m['kernel'] / m['torch']:.2f}x | "
                  f"{m['value_rel']:.1e} | {m['grad_rel']:.1e} |", flush=True)
    finally:
        if saved is None:
            os.environ.pop("REFLOW4DGS_REG_KERNEL", None)
        else:
            os.environ["REFLOW4DGS_REG_KERNEL"] = saved
    print(f"# load at the end {load_average()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
