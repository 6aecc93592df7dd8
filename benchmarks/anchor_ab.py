"""ReFlow's anchor D(x, 0) once per Gaussian (commit 4261522) against once per row, interleaved in ONE process.

    python benchmarks/anchor_ab.py [--iters 3] [--rounds 5] -- -s data/real/davis_libby -r 1 --eval \
        --coarse_iterations 0 --plugin reflow

A trainer is prepared as benchmarks/profile_step.py does (fine stage, densification off, `--warmup
0`); fine iterations then run in blocks of `--iters`, alternating "per row" (the separated
deformation called without `row_gaussian`: D(x, 0) evaluated for each of the 2M rows, the code
before 4261522) and "per Gaussian" (the default: M + U rows), so a busy machine slows both alike.
Prints the median ms per iteration of each and their ratio; asserts nothing.
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

from benchmarks.cli import split_passthrough  # noqa: E402
from benchmarks.machine import cpu_model, load_average  # noqa: E402

from baselines.thread_policy import apply_thread_policy  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    own, train_argv = split_passthrough(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iters", type=int, default=3, help="iterations per block")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(own)
    apply_thread_policy()
    from benchmarks.profile_step import _prepare, _step
    from reflow_plugin.separation import SeparatedDeformation

    trainer = _prepare(train_argv, None, 0)
    _step(trainer, 2)  # warm caches (blurred images, kernels)
    per_gaussian = SeparatedDeformation._anchored_forward
    per_row = {"on": False}

    def anchored(self, state, taus, gaussians=None):
        return per_gaussian(self, state, taus, None if per_row["on"] else gaussians)

    SeparatedDeformation._anchored_forward = anchored
    times: dict[str, list[float]] = {"per row": [], "per Gaussian": []}
    print(f"# anchor_ab: {cpu_model()}, load {load_average()}, {trainer.ctx.model.num_gaussians} Gaussians")
    try:
        for round_index in range(args.rounds):
            order = ("per row", "per Gaussian") if round_index % 2 == 0 else ("per Gaussian", "per row")
            for name in order:
                per_row["on"] = name == "per row"
                for _ in range(args.iters):
                    start = time.perf_counter()
                    _step(trainer, 1)
                    times[name].append(time.perf_counter() - start)
    finally:
        SeparatedDeformation._anchored_forward = per_gaussian
    medians = {name: statistics.median(v) * 1e3 for name, v in times.items()}
    for name, value in medians.items():
        print(f"{name}: median {value:.1f} ms over {len(times[name])} iterations")
    print(f"per Gaussian / per row: {medians['per Gaussian'] / medians['per row']:.2f}x; load {load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
