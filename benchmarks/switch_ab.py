"""ReFlow's step against the baseline's, with and without an environment switch, interleaved in ONE process.

    python benchmarks/switch_ab.py --switch REFLOW4DGS_MASK_CROP [--iters 2] [--rounds 4] -- \
        -s data/real/nvidia_balloon1 -r 4 --eval --coarse_iterations 0 --plugin reflow \
        --configs arguments/nvidia/reflow.py

Two trainers are prepared as benchmarks/profile_step.py does (fine stage, densification off,
`--warmup 0`): the arguments as given (ReFlow) and the same without the plugin
(profile_step.baseline_argv) at ReFlow's Gaussian count. Fine iterations then run in blocks of
`--iters`, one block per (trainer, switch off/on), the order reversed every other round, so a busy
machine (the 2-core machine is shared) slows every variant alike. Within a round both settings of
a trainer draw the same cameras and partner frames (its samplers' states are restored before each
block): the rows a ReFlow step deforms and the pixels its flow terms mask depend on the frames, so
blocks of different frames differ by more than most changes. The switch is read at each call
(set to 0 for "off", removed for "on", the default). Prints the median ms per iteration of each
variant (wall time and the process's CPU time), the ReFlow / baseline ratio with the switch off and
on, and on / off per trainer; asserts nothing. A switch the baseline never reads gives it two samples of one variant (a noise check).

`--densify-statistic` measures the iterations while densification runs (every iteration until
`densify_until_iter`): the densification statistic is gathered (ReFlow's extra backward of the
reconstruction losses, `Trainer._baseline_screen_grads`) but no clone, split, prune or opacity
reset happens, so the count stays fixed. `REFLOW4DGS_ACTIVE_CHANNELS` is measured this way.

Layout switches are read when the rows are rewritten, not per call: for `REFLOW4DGS_ROW_ORDER` both
trainers are prepared with it off (rows in the order the run made them: ReFlow's initial cloud, the
baseline's resampled one), and each block puts a trainer's rows in that order ("off") or in
spatial order ("on") with `GaussianModel.permute_rows` before its untimed first iteration.
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

SETTINGS = {"off": "0", "on": None}  # None: the variable removed (the code's default)
ROW_ORDER_SWITCH = "REFLOW4DGS_ROW_ORDER"  # a layout switch (module docstring)


class RowOrderLayout:
    """Puts each trainer's rows in their prepared order (off) or in spatial order (on)."""

    def __init__(self, trainers: dict) -> None:
        from baselines.fourdgs.row_order import spatial_order

        self.trainers = trainers
        self.to_sorted = {label: spatial_order(t.ctx.model.get_xyz) for label, t in trainers.items()}
        self.current = {label: "off" for label in trainers}

    def __call__(self, label: str, setting: str) -> None:
        if self.current[label] == setting:
            return
        import torch

        order = self.to_sorted[label] if setting == "on" else torch.argsort(self.to_sorted[label])
        self.trainers[label].ctx.model.permute_rows(order)
        self.current[label] = setting


def gather_densification_statistic(trainer) -> None:
    """Make every following iteration gather the densification statistic (as while densifying)
    without densifying, pruning or resetting opacities, so the Gaussian count stays fixed."""
    never = 10**9
    trainer.opt.densify_until_iter = never
    trainer.opt.densify_from_iter = trainer.opt.pruning_from_iter = trainer.opt.opacity_reset_interval = never


def _samplers(trainer) -> list:
    """The trainer's camera sampler and its plugins' pair samplers (objects with state_dict)."""
    found = [trainer.sampler]
    for plugin in trainer.hooks.plugins:
        sampler = getattr(plugin, "sampler", None)
        if sampler is not None and hasattr(sampler, "state_dict"):
            found.append(sampler)
    return found


def interleaved(trainers: dict, switch: str, iters: int, rounds: int, layout=None) -> tuple[dict, dict, dict]:
    """Median wall ms and median process CPU ms per iteration of each (trainer label, setting),
    blocks of `iters`, order alternating by round; and per trainer the median over rounds of the
    round's on / off CPU time (the two blocks of a round ran the same frames, close in time).
    `layout(label, setting)`, when given, is called before each block (a layout switch)."""
    from benchmarks.profile_step import _step

    variants = [(label, setting) for label in trainers for setting in SETTINGS]
    times: dict[tuple[str, str], list[float]] = {v: [] for v in variants}
    cpu_times: dict[tuple[str, str], list[float]] = {v: [] for v in variants}
    saved = os.environ.get(switch)
    try:
        for r in range(rounds):
            states = {label: [sampler.state_dict() for sampler in _samplers(t)] for label, t in trainers.items()}
            for label, setting in (variants if r % 2 == 0 else variants[::-1]):
                for sampler, state in zip(_samplers(trainers[label]), states[label]):
                    sampler.load_state_dict(state)
                if SETTINGS[setting] is None:
                    os.environ.pop(switch, None)
                else:
                    os.environ[switch] = SETTINGS[setting]
                trainer = trainers[label]
                if layout is not None:
                    layout(label, setting)
                _step(trainer, 1)  # the first iteration after a switch is not timed
                for _ in range(iters):
                    start, cpu = time.perf_counter(), time.process_time()
                    _step(trainer, 1)
                    times[(label, setting)].append((time.perf_counter() - start) * 1e3)
                    cpu_times[(label, setting)].append((time.process_time() - cpu) * 1e3)
    finally:
        if saved is None:
            os.environ.pop(switch, None)
        else:
            os.environ[switch] = saved
    paired = {label: statistics.median(
        sum(cpu_times[(label, "on")][r * iters:(r + 1) * iters]) / sum(cpu_times[(label, "off")][r * iters:(r + 1) * iters])
        for r in range(rounds)) for label in trainers}
    return ({v: statistics.median(t) for v, t in times.items()},
            {v: statistics.median(t) for v, t in cpu_times.items()}, paired)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, train_argv = split_passthrough(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--switch", required=True, help="environment variable whose 0 turns the change off")
    parser.add_argument("--iters", type=int, default=2, help="timed iterations per block")
    parser.add_argument("--rounds", type=int, default=4, help="blocks per variant")
    parser.add_argument("--densify-statistic", action="store_true",
                        help="gather the densification statistic every iteration (nothing is densified or pruned)")
    args = parser.parse_args(argv)
    if args.iters < 1 or args.rounds < 1:
        parser.error("--iters and --rounds must be >= 1")
    if not args.switch.isidentifier():
        parser.error(f"--switch must be an environment variable name, got {args.switch!r}")
    policy = apply_thread_policy() or "thread policy: user's"

    from benchmarks.profile_step import _prepare, _step, baseline_argv

    statistic = ", densification statistic gathered" if args.densify_statistic else ""
    print(f"# switch_ab {args.switch}{statistic}: {policy}, {cpu_model()}, load {load_average()}")
    is_layout = args.switch == ROW_ORDER_SWITCH
    saved = os.environ.get(args.switch)
    if is_layout:
        os.environ[args.switch] = "0"  # prepared in the order the run makes its rows
    try:
        plugin = _prepare(train_argv, None, 0)
        count = plugin.ctx.model.num_gaussians
        trainers = {"plugin": plugin, "baseline": _prepare(baseline_argv(train_argv), None, 0, count)}
    finally:
        if is_layout and saved is None:
            os.environ.pop(args.switch, None)
        elif is_layout:
            os.environ[args.switch] = saved
    for trainer in trainers.values():
        if args.densify_statistic:
            gather_densification_statistic(trainer)
        _step(trainer, 3)  # allocator and caches warm
    layout = RowOrderLayout(trainers) if is_layout else None
    wall, cpu, paired = interleaved(trainers, args.switch, args.iters, args.rounds, layout)
    size = f"{plugin.train_cameras[0].width}x{plugin.train_cameras[0].height}"
    print(f"\n{count} Gaussians, {size}, blocks of {args.iters} x {args.rounds} rounds; CPU: the process's "
          "CPU time (steadier than wall time on a shared machine when the step runs one thread)\n")
    print("| switch | plugin ms | baseline ms | plugin / baseline | plugin CPU ms | baseline CPU ms | CPU ratio |\n"
          "|---|---:|---:|---:|---:|---:|---:|")
    for setting in SETTINGS:
        a, b = wall[("plugin", setting)], wall[("baseline", setting)]
        ca, cb = cpu[("plugin", setting)], cpu[("baseline", setting)]
        print(f"| {setting} | {a:.1f} | {b:.1f} | {a / b:.2f}x | {ca:.1f} | {cb:.1f} | {ca / cb:.2f}x |")
    print("\n| trainer | on / off (wall) | on / off (CPU) | on / off (CPU, median of the rounds' pairs) |\n"
          "|---|---:|---:|---:|")
    for label in trainers:
        print(f"| {label} | {wall[(label, 'on')] / wall[(label, 'off')]:.3f}x | "
              f"{cpu[(label, 'on')] / cpu[(label, 'off')]:.3f}x | {paired[label]:.3f}x |")
    print(f"# load at the end {load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
