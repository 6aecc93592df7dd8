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

import sys

from .ablate import parse_runner_args, start_runs

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
    args, variants, extra = parse_runner_args(argv, "python -m reflow_plugin.sweep", __doc__.splitlines()[0],
                                              "variants", VARIANTS)
    started = start_runs(args, variants, extra, "sweep", table=VARIANTS)
    if started is None:
        return 2
    specs, failures = started
    for failure in failures:
        print(f"error: {failure}", file=sys.stderr)
    print(f"[sweep] {len(specs) - len(failures)} runs in {args.out}; next: python -m reflow_plugin.report {args.out} "
          "--pareto")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
