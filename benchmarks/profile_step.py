"""Profile fine-stage training iterations: per-phase medians and the aten ops by wall time.

    python benchmarks/profile_step.py --model_from output/skating/point_cloud/iteration_2000 -- --configs arguments/synthetic/default.py
    python benchmarks/profile_step.py                       # trains coarse + 500 fine iterations first
    python benchmarks/profile_step.py --warmup 0 --gaussians 2000 -- --configs none \
        -s data/synthetic/skating_64x48 --coarse_iterations 0        # 4DGS's bare model, 2k Gaussians

    python benchmarks/profile_step.py --warmup 0 --iters 10 --compare_baseline -- -s data/real/nvidia_balloon1 \
        -r 4 --eval --coarse_iterations 0 --plugin reflow --configs arguments/nvidia/reflow.py
                                    # ReFlow's step, then the baseline's at the same count and size

Everything after ``--`` goes to train.py's parser (default: the embedded scene with its config).
The model is a trained one (``--model_from``, a point_cloud/iteration_N folder written with the
same config) or the result of a short warm-up (full coarse stage, ``--warmup`` fine iterations),
so the Gaussian count is the one training spends its time at. Then ``--iters`` fine iterations
run twice: once timed by the trainer's StageTimer (medians per phase, no instrumentation), once
with every aten op timed (``op_table``: wall time per op, summed over the iterations and divided
by their number; forward, backward and optimizer ops alike). Densification and the opacity reset are switched off for the measured
iterations (their cost, amortised over their interval, is reported by benchmarks/train_baseline.py),
so every measured iteration does the same work. Prints Markdown tables (docs/PROFILE.md holds the
latest ones): the phases, the pieces inside them (each plugin hook, the baseline losses, the
densification statistic's extra backward, autograd's backward) and the aten ops.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(0, str(REPO_ROOT))

from benchmarks.cli import split_passthrough  # noqa: E402
from benchmarks.machine import cpu_model, load_average  # noqa: E402

from baselines.thread_policy import apply_thread_policy  # noqa: E402

PHASES = ("deform_project", "rasterize", "loss_backward", "densify_step")


def _prepare(train_argv: list[str], model_from: Path | None, warmup: int, gaussians: int | None = None):
    """A trainer in its fine stage with a trained model and densification off."""
    import torch

    from baselines.fourdgs.app import build_trainer
    from baselines.fourdgs.row_order import order_rows

    if not any(a in ("-m", "--model_path") or a.startswith("--model_path=") for a in train_argv):
        import tempfile  # a scratch model folder, not output/<scene> (which may hold a real run)

        train_argv = ["-m", tempfile.mkdtemp(prefix="profile_step_"), *train_argv]
    trainer = build_trainer(["--quiet", "--test_iterations", "-1", "--save_iterations", "-1", *train_argv])
    if model_from is not None:
        trainer.load_model_from(model_from)
    else:
        trainer.build()
        if gaussians is not None:  # resample the initial cloud to the requested count (1% jitter)
            cloud = trainer.ctx.point_cloud
            points = torch.as_tensor(cloud.points, dtype=torch.float32)
            generator = torch.Generator().manual_seed(0)
            pick = torch.randint(len(points), (gaussians,), generator=generator)
            jitter = 0.01 * trainer.cameras_extent * torch.randn(gaussians, 3, generator=generator)
            colors = torch.as_tensor(cloud.colors, dtype=torch.float32)[pick]
            trainer.ctx.model.create_from_pcd(points[pick] + jitter, colors, trainer.cameras_extent,
                                              device=trainer.device)
            order_rows(trainer.ctx.model)  # as the trainer lays out any new rows (row_order.py)
        for stage, total in (("coarse", trainer.opt.coarse_iterations), ("fine", warmup)):
            trainer._begin_stage(stage, total)
            for iteration in range(1, total + 1):
                trainer.ctx.iteration = iteration
                trainer.train_step()
    trainer._begin_stage("fine", trainer.opt.iterations)
    # the measured iterations: no densification or opacity reset, but the same losses and step
    trainer.opt.densify_until_iter = 0
    trainer.opt.opacity_reset_interval = 10**9
    trainer.ctx.iteration = max(trainer.opt.pruning_from_iter, trainer.opt.densify_until_iter) + 1
    return trainer


def _step(trainer, count: int) -> None:
    for _ in range(count):
        trainer.ctx.iteration += 1
        trainer.train_step()


def phase_medians(trainer, iters: int) -> tuple[dict[str, float], float]:
    """Median ms per phase and median ms per whole iteration over ``iters`` timed iterations."""
    per_phase: dict[str, list[float]] = {p: [] for p in PHASES}
    totals = []
    for _ in range(iters):
        before = {p: trainer.timer.total[p] for p in PHASES}
        start = time.perf_counter()
        _step(trainer, 1)
        totals.append((time.perf_counter() - start) * 1e3)
        for p in PHASES:
            per_phase[p].append((trainer.timer.total[p] - before[p]) * 1e3)
    return {p: statistics.median(v) for p, v in per_phase.items()}, statistics.median(totals)


HOOK_METHODS = ("call", "first", "merged", "combined_mask", "product")


def detail_medians(trainer, iters: int) -> dict[str, float]:
    """Median ms per iteration of the pieces inside the phases: each plugin hook (by name), the
    baseline losses, the densification statistic's extra backward; "backward (rest)" is the
    loss_backward phase less the losses and hooks timed inside it (autograd's backward pass).

    The hooks and methods are wrapped by timing closures on this trainer only (a few microseconds
    per call); the plugin's own work inside a hook (e.g. ReFlow's flow losses in extra_losses) is
    what the hook's row shows."""
    spent: dict[str, float] = defaultdict(float)

    def timed(label, fn):
        def wrapper(*args, **kwargs):
            name = label(args)
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - start
        return wrapper

    originals = {}
    for method in HOOK_METHODS:
        originals[("hooks", method)] = getattr(trainer.hooks, method)
        setattr(trainer.hooks, method, timed(lambda a: f"hook {a[0]}", originals[("hooks", method)]))
    for method, label in (("baseline_losses", "baseline losses"), ("_baseline_screen_grads", "densify statistic backward")):
        originals[("trainer", method)] = getattr(trainer, method)
        setattr(trainer, method, timed(lambda a, label=label: label, originals[("trainer", method)]))
    rows: dict[str, list[float]] = defaultdict(list)
    try:
        for _ in range(iters):
            spent.clear()
            before = trainer.timer.total["loss_backward"]
            _step(trainer, 1)
            inside = trainer.timer.total["loss_backward"] - before
            in_loss_phase = sum(v for k, v in spent.items() if k in (
                "baseline losses", "densify statistic backward", "hook extra_losses", "hook pre_backward",
                "hook post_backward"))  # loss_weights runs inside baseline_losses
            spent["backward (rest)"] = inside - in_loss_phase
            for key, value in spent.items():
                rows[key].append(value * 1e3)
    finally:
        for (owner, method) in originals:
            target = trainer.hooks if owner == "hooks" else trainer
            delattr(target, method)  # the instance attribute shadowed the class's method
    return {k: statistics.median(v + [0.0] * (iters - len(v))) for k, v in rows.items()}


def op_table(trainer, iters: int, top: int) -> tuple[list[tuple[str, float, float, float]], float, float]:
    """Wall time inside each aten op, timed around the op's call by a TorchDispatchMode.

    Returns ([(op, ms per iteration, share of the time in ops, calls per iteration)], ms per
    iteration in ops, aten calls per iteration). torch.profiler was tried first: on this VM it
    charged element-wise ops 10-25x their real cost (threshold_backward on [10k, 64]: 3.8 ms under
    the profiler, 0.1-0.9 ms timed directly), so its table pointed at the wrong ops. The timing
    mode adds Python overhead per op, so the sum over ops exceeds the plain iteration time; the
    shares are what to read.
    """
    from torch.utils._python_dispatch import TorchDispatchMode

    seconds: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)

    class OpTimer(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            start = time.perf_counter()
            out = func(*args, **(kwargs or {}))
            name = str(func.overloadpacket)
            seconds[name] += time.perf_counter() - start
            calls[name] += 1
            return out

    with OpTimer():
        _step(trainer, iters)
    total = sum(seconds.values())
    rows = sorted(seconds, key=seconds.get, reverse=True)[:top]
    table = [(name, seconds[name] * 1e3 / iters, seconds[name] / total, calls[name] / iters) for name in rows]
    return table, total * 1e3 / iters, sum(calls.values()) / iters


def baseline_argv(train_argv: list[str]) -> list[str]:
    """The same training arguments without the plugin: ``--plugin NAME`` dropped, the plugin's own
    flags (its parameter groups' fields, ``--disable`` / ``--enable``) dropped with their values, and a
    plugin config (``.../reflow.py``) replaced by the family's ``default.py`` beside it (the 4DGS
    config it builds on)."""
    dropped = _plugin_flags(train_argv)
    out, skip_value, skip_values = [], False, False
    for k, arg in enumerate(train_argv):
        if skip_value:
            skip_value = False
            continue
        if skip_values and not arg.startswith("--"):
            continue
        skip_values = False
        if arg == "--plugin":
            skip_value = True
            continue
        if arg.startswith("--plugin="):
            continue
        if arg.split("=", 1)[0] in dropped:
            skip_values = "=" not in arg  # the values that follow (a list flag takes several)
            continue
        if k > 0 and train_argv[k - 1] == "--configs" and Path(arg).name != "default.py":
            sibling = Path(arg).with_name("default.py")
            arg = str(sibling) if sibling.exists() else arg
        out.append(arg)
    return out


def _plugin_flags(train_argv: list[str]) -> set[str]:
    """``--name`` and ``--no-name`` of every field of the named plugins' parameter groups, plus the
    component switches: flags the baseline's parser does not know."""
    import dataclasses

    from baselines.fourdgs.plugins import load_plugin_class

    names = [train_argv[k + 1] for k, a in enumerate(train_argv[:-1]) if a == "--plugin"]
    names += [a.split("=", 1)[1] for a in train_argv if a.startswith("--plugin=")]
    flags = {"--disable", "--enable"}
    for name in (n for item in names for n in item.split(",") if n):
        for group in load_plugin_class(name).param_groups.values():
            for field in dataclasses.fields(group):
                flags |= {f"--{field.name}", f"--no-{field.name}"}
    return flags


def profile(train_argv: list[str], args, gaussians: int | None) -> dict:
    """Phase medians, the pieces inside the phases and the op table of one trainer."""
    trainer = _prepare(train_argv, args.model_from, args.warmup, gaussians)
    _step(trainer, 3)  # allocator and caches warm
    phases, total = phase_medians(trainer, args.iters)
    details = detail_medians(trainer, args.iters)
    ops, ops_ms, op_calls = op_table(trainer, args.iters, args.top)
    model = trainer.ctx.model
    cam = trainer.train_cameras[0]
    return dict(phases=phases, total=total, details=details, ops=ops, ops_ms=ops_ms, op_calls=op_calls,
                gaussians=model.num_gaussians, size=f"{cam.width}x{cam.height}", batch=trainer.opt.batch_size,
                params=sum(p.numel() for g in model.optimizer.param_groups for p in g["params"]),
                plugins=",".join(type(p).__name__ for p in trainer.hooks.plugins) or "none")


def print_profile(result: dict) -> None:
    phases, total = result["phases"], result["total"]
    print(f"## {result['plugins']}: {result['gaussians']} Gaussians, {result['params'] / 1e6:.2f}M parameters, "
          f"{result['size']}, batch {result['batch']}\n")
    print("| phase | median ms / iteration | share |\n|---|---:|---:|")
    for p in PHASES:
        print(f"| {p} | {phases[p]:.1f} | {phases[p] / total:.0%} |")
    other = total - sum(phases.values())
    print(f"| other (lr, sampler, metrics, log) | {other:.1f} | {other / total:.0%} |")
    print(f"| **iteration** | **{total:.1f}** | |\n")
    print("| inside the phases | median ms / iteration |\n|---|---:|")
    for name, ms in sorted(result["details"].items(), key=lambda kv: -kv[1]):
        if ms >= 0.05:
            print(f"| {name} | {ms:.1f} |")
    print()
    print(f"{result['op_calls']:.0f} aten calls per iteration, {result['ops_ms']:.1f} ms inside them "
          f"(timed, with the timing overhead)\n")
    print("| op | ms / iteration | share of op time | calls / iteration |\n|---|---:|---:|---:|")
    for name, ms, share, calls in result["ops"]:
        print(f"| `{name}` | {ms:.2f} | {share:.1%} | {calls:.0f} |")
    print()


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, train_argv = split_passthrough(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model_from", type=Path, help="a point_cloud/iteration_N folder trained with the same config")
    parser.add_argument("--warmup", type=int, default=500, help="fine iterations before measuring (no --model_from)")
    parser.add_argument("--gaussians", type=int, help="resample the initial cloud to this many (no --model_from)")
    parser.add_argument("--iters", type=int, default=30)
    parser.add_argument("--top", type=int, default=20)
    parser.add_argument("--compare_baseline", action="store_true",
                        help="then profile the same arguments without the plugin (see baseline_argv) at the "
                             "plugin run's Gaussian count, in this process, and print the ratios")
    args = parser.parse_args(argv)
    if args.compare_baseline and args.model_from is not None:
        parser.error("--compare_baseline resamples the baseline's cloud: use it without --model_from")
    policy = apply_thread_policy() or "thread policy: user's"

    import torch

    print(f"# profile_step: torch {torch.__version__}, {policy}, {cpu_model()}, load {load_average()}")
    print(f"# command: python benchmarks/profile_step.py {' '.join(sys.argv[1:])}\n")
    results = [profile(train_argv, args, args.gaussians)]
    if args.compare_baseline:
        results.append(profile(baseline_argv(train_argv), args, results[0]["gaussians"]))
    for result in results:
        print_profile(result)
    if len(results) == 2:
        plugin, base = results
        print(f"# load at the end {load_average()}\n")
        print(f"| phase | {plugin['plugins']} ms | baseline ms | ratio |\n|---|---:|---:|---:|")
        for p in (*PHASES, "iteration"):
            a = plugin["total"] if p == "iteration" else plugin["phases"][p]
            b = base["total"] if p == "iteration" else base["phases"][p]
            print(f"| {p} | {a:.1f} | {b:.1f} | {a / max(b, 1e-9):.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
