"""Resident memory of training: one fine iteration phase by phase at a given count, or a whole run's course.

    python benchmarks/memory_step.py --gaussians 90000 -- -s data/real/davis_dog -r 2 --eval --coarse_iterations 0
    python benchmarks/memory_step.py --gaussians 20000 --ops -- -s data/real/davis_dog -r 2 --eval --coarse_iterations 0
    python benchmarks/memory_step.py --trajectory --every 50 -- -s data/real/davis_dog -r 2 --eval \
        --coarse_iterations 300 --iterations 400 --densification_interval 21 --pruning_interval 21

Everything after ``--`` goes to train.py's parser (no ``--configs``: the capture family's default,
as train.py and benchmarks/convergence.py run it). The allocator and OpenMP settings are train.py's
(thread_policy.py).

One iteration (default): the trainer is built and put in its fine stage by
benchmarks/profile_step.py's ``_prepare`` (densification and opacity reset off, so every measured
iteration does the same work): ``--model_from`` loads a trained point_cloud/iteration_N folder,
else ``--gaussians`` resamples the initial cloud to that count with 1% jitter (pass
``--coarse_iterations 0``: ``_prepare`` trains the coarse stage first). After one unmeasured
iteration, ``--iters`` iterations run; for each phase of the trainer's StageTimer (deform_project,
rasterize, loss_backward, densify_step) the kernel's peak RSS (``VmHWM``, reset through
``/proc/self/clear_refs`` at the phase's start) is read at its end. Printed per phase, the largest
over the iterations: RSS at the phase's start and the peak's rise above it (MiB); and the minor
page faults per iteration. ``--ops``: one more iteration under ``torch.profiler`` with
``profile_memory``, its allocations and frees replayed in order: the most bytes live at once
(the iteration's own need, whatever the allocator keeps besides) and, at that moment, which ops
allocated them.

``--trajectory``: train from the initial cloud as train.py does (densification on) and print every
``--every`` iterations the count, RSS, its peak so far and glibc's heap (in use, and freed but
kept). A run's memory grows with the changes of count, not with one iteration's need (see
docs/PROFILE.md, "Memory of a training run"); ``--no_release`` keeps the trainer from giving
freed memory back, and ``ONEDNN_PRIMITIVE_CACHE_CAPACITY=1024 LRU_CACHE_CAPACITY=1024`` in the
environment restore the caches' defaults: both together are the behaviour before 2026-11-27.

One measurement per process: the allocator's state after one count or run would change the
next one's figures.
"""
from __future__ import annotations

import argparse
import ctypes
import re
import resource
import statistics
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

REPO_ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(0, str(REPO_ROOT))

from benchmarks.cli import split_passthrough  # noqa: E402
from benchmarks.machine import cpu_model, load_average  # noqa: E402
from benchmarks.profile_step import PHASES, _prepare, _step  # noqa: E402

from baselines.thread_policy import apply_thread_policy  # noqa: E402

MIB = 1024.0


def _status_kib(field: str) -> int:
    """A ``/proc/self/status`` field in KiB (VmRSS, VmHWM)."""
    with open("/proc/self/status") as status:
        match = re.search(rf"^{field}:\s+(\d+) kB", status.read(), re.MULTILINE)
    if match is None:
        raise RuntimeError(f"/proc/self/status has no {field}")
    return int(match.group(1))


def reset_peak() -> None:
    """Reset the kernel's peak RSS (VmHWM) of this process to its current RSS (Linux >= 4.0)."""
    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")


class PhasePeaks:
    """A stand-in for the trainer's StageTimer context: per phase, RSS at its start and the peak
    rise above that (KiB), the largest over the calls; still times the phase on the real timer."""

    def __init__(self, timer) -> None:
        self.timer = timer
        self.start_kib: dict[str, int] = defaultdict(int)
        self.rise_kib: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        reset_peak()
        start = _status_kib("VmRSS")
        try:
            with self.timer(name):
                yield
        finally:
            self.start_kib[name] = max(self.start_kib[name], start)
            self.rise_kib[name] = max(self.rise_kib[name], _status_kib("VmHWM") - start)

    def __getattr__(self, name: str):  # total, count, means: the real timer's
        return getattr(self.timer, name)


def measure_phases(trainer, iters: int) -> tuple[PhasePeaks, int, int, float, float]:
    """Run ``iters`` iterations with per-phase peaks; also (RSS before them, peak of the whole
    iterations, median seconds per iteration, minor page faults per iteration) in KiB / seconds."""
    peaks = PhasePeaks(trainer.timer)
    trainer.timer = peaks
    before = _status_kib("VmRSS")
    reset_peak()
    seconds = []
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    try:
        for _ in range(iters):
            start = time.perf_counter()
            _step(trainer, 1)
            seconds.append(time.perf_counter() - start)
    finally:
        trainer.timer = peaks.timer
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / iters
    # the phase resets lowered VmHWM: the whole iterations' peak is the largest phase peak
    whole = max(peaks.start_kib[p] + peaks.rise_kib[p] for p in peaks.start_kib)
    seconds.sort()
    return peaks, before, whole, seconds[len(seconds) // 2], faults


def op_memory(trainer) -> tuple[list[tuple[str, float, int]], list[tuple[str, float, int]], float]:
    """One iteration under torch.profiler(profile_memory=True), its allocations replayed in order.

    Returns (the blocks live at the moment the most bytes were live, grouped by the op that
    allocated them: [(op, MiB, blocks)] largest first; every allocation of the iteration grouped
    the same way; that peak in MiB above the iteration's start). Blocks allocated before the
    iteration (parameters, optimizer state) are not in the groups; their frees lower the count.
    """
    from torch._C._profiler import _EventType
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        _step(trainer, 1)
    events = []  # (time, ptr, bytes, op)

    def walk(nodes) -> None:
        for node in nodes:
            if node.tag == _EventType.Allocation:
                parent = node.parent.name if node.parent is not None else "(outside ops)"
                fields = node.extra_fields
                events.append((node.start_time_ns, fields.ptr, fields.alloc_size, parent))
            walk(node.children)

    walk(prof.profiler.kineto_results.experimental_event_tree())
    events.sort(key=lambda e: e[0])
    live: dict[int, tuple[int, str]] = {}
    allocated: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    total = peak = 0
    at_peak: dict[int, tuple[int, str]] = {}
    for _, ptr, size, op in events:
        total += size
        if size > 0:
            live[ptr] = (size, op)
            allocated[op][0] += size
            allocated[op][1] += 1
        else:
            live.pop(ptr, None)
        if total > peak:
            peak, at_peak = total, dict(live)
    held: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for size, op in at_peak.values():
        held[op][0] += size
        held[op][1] += 1

    def table(groups: dict[str, list[int]]) -> list[tuple[str, float, int]]:
        return sorted(((op, b / MIB**2, n) for op, (b, n) in groups.items()), key=lambda r: -r[1])

    return table(held), table(allocated), peak / MIB**2


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (glibc >= 2.33): the main heap's bytes, free and in use."""

    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


def heap_mib() -> tuple[float, float] | None:
    """(MiB in use, MiB free but kept) of glibc's heap, or None off glibc >= 2.33."""
    try:
        mallinfo2 = ctypes.CDLL(None).mallinfo2
    except (OSError, AttributeError):
        return None
    mallinfo2.restype = _MallInfo2
    info = mallinfo2()
    return info.uordblks / MIB**2, info.fordblks / MIB**2


def trajectory(train_argv: list[str], every: int, release: bool) -> None:
    """Train from the initial cloud as train.py does (coarse, then fine; densification as the flags
    say; no evaluation or saving) and print a row every ``every`` iterations: the Gaussian count,
    RSS and its peak so far, glibc's heap in use and free, the median step time of the rows'
    window. ``release=False``: the trainer does not give freed memory back after a change of
    count (the behaviour before 2026-11-27)."""
    import tempfile

    from baselines.fourdgs import trainer as trainer_module
    from baselines.fourdgs.app import build_trainer

    if not release:
        trainer_module.release_free_memory = lambda: False
    trainer = build_trainer(["-m", tempfile.mkdtemp(prefix="memory_step_"), "--quiet", "--test_iterations", "-1",
                             "--save_iterations", "-1", *train_argv])
    trainer.build()
    print("| stage | iteration | Gaussians | RSS MiB | peak RSS MiB | heap in use MiB | heap free MiB "
          "| median s / iteration | page faults / iteration |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for stage, total in (("coarse", trainer.opt.coarse_iterations), ("fine", trainer.opt.iterations)):
        trainer._begin_stage(stage, total)
        seconds: list[float] = []
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for iteration in range(1, total + 1):
            trainer.ctx.iteration = iteration
            start = time.perf_counter()
            trainer.train_step()
            seconds.append(time.perf_counter() - start)
            if iteration % every == 0 or iteration == total:
                heap = heap_mib()
                used, free = (f"{heap[0]:.0f}", f"{heap[1]:.0f}") if heap else ("-", "-")
                print(f"| {stage} | {iteration} | {trainer.ctx.model.num_gaussians} | {_status_kib('VmRSS') / MIB:.0f} "
                      f"| {_status_kib('VmHWM') / MIB:.0f} | {used} | {free} | {statistics.median(seconds):.2f} "
                      f"| {(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / len(seconds):.0f} |",
                      flush=True)
                seconds, faults = [], resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, train_argv = split_passthrough(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model_from", type=Path, help="a point_cloud/iteration_N folder trained with the same config")
    parser.add_argument("--gaussians", type=int, help="resample the initial cloud to this many (no --model_from)")
    parser.add_argument("--warmup", type=int, default=0, help="fine iterations before measuring (no --model_from)")
    parser.add_argument("--iters", type=int, default=3, help="measured iterations (after 1 unmeasured)")
    parser.add_argument("--ops", action="store_true", help="then one iteration under torch.profiler: MiB per op")
    parser.add_argument("--top", type=int, default=15, help="ops listed with --ops")
    parser.add_argument("--trajectory", action="store_true",
                        help="instead: train from the initial cloud (densification on) and print the memory every "
                             "--every iterations")
    parser.add_argument("--every", type=int, default=100, help="iterations between rows of --trajectory")
    parser.add_argument("--no_release", action="store_true",
                        help="with --trajectory: the trainer keeps freed memory after a change of count (as before "
                             "2026-11-27)")
    args = parser.parse_args(argv)
    policy = apply_thread_policy() or "thread policy: user's"

    import torch

    print(f"# memory_step: torch {torch.__version__}, {policy}, {cpu_model()}, load {load_average()}")
    print(f"# command: python benchmarks/memory_step.py {' '.join(sys.argv[1:])}\n")
    if args.trajectory:
        trajectory(train_argv, args.every, release=not args.no_release)
        print(f"\n# load at the end {load_average()}")
        return 0
    trainer = _prepare(train_argv, args.model_from, args.warmup, args.gaussians)
    _step(trainer, 1)  # the first iteration's one-off allocations (optimizer state) are not the step's
    peaks, before, whole, seconds, faults = measure_phases(trainer, args.iters)
    model, cam = trainer.ctx.model, trainer.train_cameras[0]
    print(f"## {model.num_gaussians} Gaussians, {cam.width}x{cam.height}, batch {trainer.opt.batch_size}, "
          f"{args.iters} iterations, median {seconds:.2f} s / iteration, "
          f"{faults:.0f} minor page faults / iteration\n")
    print(f"RSS before the iterations {before / MIB:.0f} MiB, peak during them {whole / MIB:.0f} MiB "
          f"(+{(whole - before) / MIB:.0f})\n")
    print("| phase | RSS at start MiB | peak rise MiB |\n|---|---:|---:|")
    for phase in PHASES:
        print(f"| {phase} | {peaks.start_kib[phase] / MIB:.0f} | {peaks.rise_kib[phase] / MIB:.0f} |")
    print()
    if args.ops:
        held, allocated, live_peak = op_memory(trainer)
        print(f"Under the profiler: at most {live_peak:.0f} MiB allocated and not yet freed above the "
              "iteration's start; at that moment, by the op that allocated them:\n")
        print("| op | MiB live at the peak | blocks |\n|---|---:|---:|")
        for name, mib, count in held[:args.top]:
            print(f"| `{name}` | {mib:.0f} | {count} |")
        print("\nEvery allocation of the iteration, by op:\n")
        print("| op | MiB allocated | blocks |\n|---|---:|---:|")
        for name, mib, count in allocated[:args.top]:
            print(f"| `{name}` | {mib:.0f} | {count} |")
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
