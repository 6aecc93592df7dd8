"""Accuracy against training time over the main cost knobs, for picking a budget.

    python -m reflow_plugin.sweep -s data/synthetic/skating -o output/sweep [--variants ...]
                                  [--jobs N] [--executor local|slurm] [-- extra train.py flags]
    python -m reflow_plugin.report output/sweep --pareto      # plot + Pareto front

Each variant is one knob moved away from the default run of its method (baseline 4DGS or
ReFlow), everything else equal, so the sweep shows what each knob buys:

    iterations   half the fine iterations (schedule scaled: lr decay, densification window)
    resolution   images at half size (-r 2)
    budget       at most 3000 Gaussians (densification stops there)
    pair_window  ReFlow pairs up to 4 frames apart instead of 2
    flow_every   ReFlow's flow terms every 2nd iteration only

Runs are ordinary train.py runs in OUT/<scene>/<variant>, scheduled, resumed and marked done
exactly like the ablation runner's (`reflow_plugin.ablate`: submitit, `ablate_done.json`). Every
run records held-out PSNR with the training time spent so far, so `report --pareto` can draw the
curves and the front of final (time, PSNR) points.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .ablate import AblationError, is_done, make_executor, plan, resolve_scenes, run_all

_HALF_SCHEDULE = ["--iterations", "1000", "--position_lr_max_steps", "1000", "--densify_until_iter", "750"]
_REFLOW = ["--plugin", "reflow"]

VARIANTS: dict[str, tuple[str, list[str]]] = {
    "baseline": ("4DGS", []),
    "baseline_iterations": ("4DGS, half iterations", _HALF_SCHEDULE),
    "baseline_resolution": ("4DGS, half resolution", ["-r", "2"]),
    "baseline_budget": ("4DGS, <= 3000 Gaussians", ["--densify_max_gaussians", "3000"]),
    "reflow": ("ReFlow", _REFLOW),
    "reflow_iterations": ("ReFlow, half iterations", _REFLOW + _HALF_SCHEDULE),
    "reflow_resolution": ("ReFlow, half resolution", _REFLOW + ["-r", "2"]),
    "reflow_budget": ("ReFlow, <= 3000 Gaussians", _REFLOW + ["--densify_max_gaussians", "3000"]),
    "reflow_pair_window": ("ReFlow, pairs up to 4 frames apart", _REFLOW + ["--pair_window", "4"]),
    "reflow_flow_every": ("ReFlow, flow terms every 2nd iteration", _REFLOW + ["--flow_every", "2"]),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        extra, argv = argv[argv.index("--") + 1:], argv[:argv.index("--")]
    parser = argparse.ArgumentParser(prog="python -m reflow_plugin.sweep", description=__doc__.splitlines()[0])
    parser.add_argument("-s", "--source", required=True, help="a scene folder or suite:synthetic")
    parser.add_argument("-o", "--out", type=Path, required=True)
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {list(VARIANTS)}")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--executor", default="local", choices=("local", "slurm"))
    parser.add_argument("--timeout_min", type=int, default=240)
    parser.add_argument("--slurm_partition")
    args = parser.parse_args(argv)
    try:
        variants = [v for v in args.variants.split(",") if v]
        specs = plan(resolve_scenes(args.source), variants, args.out, extra, table=VARIANTS)
        executor = make_executor(args.executor, args.out / "_submitit", args.timeout_min, args.slurm_partition)
    except AblationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    done = sum(is_done(s) for s in specs)
    if done:
        print(f"[sweep] {done} of {len(specs)} runs already done (kept)")
    failures = run_all(specs, executor, args.jobs)
    for failure in failures:
        print(f"error: {failure}", file=sys.stderr)
    print(f"[sweep] {len(specs) - len(failures)} runs in {args.out}; next: python -m reflow_plugin.report {args.out} "
          "--pareto")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
