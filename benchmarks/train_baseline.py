"""Train the 4DGS baseline on the synthetic suite and print speed, memory and quality per scene.

    python benchmarks/train_baseline.py                                      # 100 + 500 iterations, 6 scenes
    python benchmarks/train_baseline.py --full                               # the shipped config's schedule
    python benchmarks/train_baseline.py --scenes balloon,truck --iterations 500 --threads 1 --json out.json
    python benchmarks/train_baseline.py --deformation                        # + benchmarks/deformation.py

Every scene is generated with `baselines.synthetic` into `<data_root>/<name>` (or
`<name>_<W>x<H>` for a non-default `--size`), reused when its scene.json matches the spec, and
trained in a fresh subprocess (so the peak RSS is that run's) with `OMP_WAIT_POLICY=PASSIVE` in
its environment. The run is the one train.py does (`build_trainer` + `Trainer.train`) with the
config file and the schedule overrides below; intermediate test evaluations and saves are off
(`--test_iterations [] --save_iterations []`; the trainer still saves at each stage's end).

Measured per scene:
- iterations/s per stage: iterations / the stage's wall time (on_stage_start to on_stage_end,
  which includes the end-of-stage point-cloud save);
- process CPU time per iteration (all threads; steadier than wall time on a shared machine);
- the trainer's StageTimer phases per stage, median ms per iteration (read at every iteration's
  end) and share of the median iteration: deform_project (deformation + projection of the
  batch), rasterize (compositing), loss_backward (losses and the WHOLE backward pass, i.e.
  through compositing, projection and deformation), densify_step (densification + optimizer
  step); "other" is the median iteration minus the phases' medians (learning-rate update,
  sampler, per-iteration PSNR metric and log); the stage's mean ms per iteration beside it
  includes the densification steps and the end-of-stage save;
- peak RSS: `resource.getrusage(RUSAGE_SELF).ru_maxrss` of the worker process (Python, torch,
  the loaded scene and training). tracemalloc is not used: torch's CPU allocator bypasses it;
- final and peak number of Gaussians;
- test-view PSNR / SSIM (held-out every 8th frame, `evaluate_cameras`, the fine stage) before
  training (the initial cloud) and after, and the PSNR on the training views after.

The timings come from a benchmark-only plugin (`bench_probe`) that only reads the trainer's
state at the hook points; it changes nothing in training.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(0, str(REPO_ROOT))

from machine import cpu_model, load_average  # noqa: E402  (benchmarks/machine.py, beside this script)

from baselines.thread_policy import apply_thread_policy  # noqa: E402

DEFAULT_SCENES = ("balloon", "playground", "skating", "truck", "umbrella", "static")
DEFAULT_CONFIG = REPO_ROOT / "arguments" / "synthetic" / "default.py"
# The default (short) schedule: the shipped config's stage lengths (300 + 2000) cut to 100 + 500 so
# the six scenes train in about seven minutes on 2 cores; everything else comes from the config
# unchanged (so densification, every 50 iterations from iteration 100, runs through the whole
# fine stage, and the position learning rate, decaying over 3000 steps, is still high at its end).
SHORT_COARSE, SHORT_FINE = 100, 500
PHASES = ("deform_project", "rasterize", "loss_backward", "densify_step")
PHASE_LABELS = {"deform_project": "deform+project", "rasterize": "rasterize",
                "loss_backward": "loss+backward", "densify_step": "densify+step"}


# ------------------------------------------------------------------------------ scene cache
def scene_dir(data_root: Path, name: str, size: tuple[int, int] | None) -> Path:
    """<data_root>/<name>, or <name>_<W>x<H> for a non-default size."""
    return data_root / (name if size is None else f"{name}_{size[0]}x{size[1]}")


def ensure_scene(data_root: Path, name: str, size: tuple[int, int] | None) -> tuple[Path, dict]:
    """Generate the scene unless a matching one (same spec) is already there; return (path, scene.json)."""
    from baselines.synthetic import get_scene, simulate

    spec = get_scene(name)
    if size is not None:
        spec = spec.with_overrides(width=size[0], height=size[1])
    path = scene_dir(data_root, name, size)
    wanted = json.loads(json.dumps(spec.to_dict()))  # tuples -> lists, as scene.json stores them
    info_path = path / "scene.json"
    if info_path.is_file() and (path / "poses_bounds.npy").is_file():
        info = json.loads(info_path.read_text())
        if info.get("spec") == wanted:
            return path, info
        print(f"[bench] {path}: cached scene differs from the current spec; regenerating", file=sys.stderr)
    start = time.perf_counter()
    simulate(spec, path, progress=False)
    print(f"[bench] generated {name} ({spec.width}x{spec.height}, {spec.frames} frames) into {path} "
          f"in {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return path, json.loads(info_path.read_text())


# ------------------------------------------------------------------------------ worker side
def _maxrss_bytes() -> int:
    # ru_maxrss is in KiB on Linux, in bytes on macOS.
    scale = 1 if sys.platform == "darwin" else 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def _make_probe_class():
    """The benchmark plugin (defined lazily: the host is imported only in workers)."""
    from baselines.fourdgs.plugins import Plugin

    class BenchProbe(Plugin):
        """Reads wall/CPU clocks, the trainer's StageTimer and the Gaussian count at hook points."""

        name = "bench_probe"

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.timer = None  # the trainer's StageTimer, set by the worker after build_trainer
            self.stages: dict[str, dict[str, Any]] = {}
            self.peak_gaussians = 0
            self._start: tuple[float, float, dict[str, float], dict[str, int]] | None = None
            self._last: tuple[float, dict[str, float]] | None = None  # (wall, phase totals) at the last iteration end
            self._samples: dict[str, list[float]] = {}  # per-iteration seconds per phase, and "iteration"

        def _snapshot(self) -> tuple[float, float, dict[str, float], dict[str, int]]:
            return (time.perf_counter(), time.process_time(), dict(self.timer.total), dict(self.timer.count))

        def on_stage_start(self, ctx) -> None:
            self._start = self._snapshot()
            self._last = (self._start[0], dict(self._start[2]))
            self._samples = {}
            self.peak_gaussians = max(self.peak_gaussians, ctx.model.num_gaussians)
            self.stages[ctx.stage] = {"gaussians_start": ctx.model.num_gaussians}

        def on_iteration_end(self, ctx) -> None:
            self.peak_gaussians = max(self.peak_gaussians, ctx.model.num_gaussians)
            now, totals = time.perf_counter(), dict(self.timer.total)
            last_wall, last_totals = self._last
            self._samples.setdefault("iteration", []).append(now - last_wall)
            for phase, seconds in totals.items():
                self._samples.setdefault(phase, []).append(seconds - last_totals.get(phase, 0.0))
            self._last = (now, totals)

        def on_stage_end(self, ctx) -> None:
            wall, cpu, total, count = self._snapshot()
            wall0, cpu0, total0, count0 = self._start
            iterations = ctx.stage_iterations
            phases = {k: 1000.0 * (total[k] - total0.get(k, 0.0)) / max(1, count[k] - count0.get(k, 0))
                      for k in total}
            self.stages[ctx.stage].update(
                iterations=iterations, wall_s=wall - wall0, cpu_s=cpu - cpu0,
                it_per_s=iterations / max(wall - wall0, 1e-12),
                ms_per_it=1000.0 * (wall - wall0) / max(1, iterations),
                cpu_ms_per_it=1000.0 * (cpu - cpu0) / max(1, iterations),
                phases_ms=phases, gaussians_end=ctx.model.num_gaussians,
                phases_median_ms={k: 1000.0 * statistics.median(v) for k, v in self._samples.items() if v},
            )

    return BenchProbe


def _mean_metrics(trainer, cameras, stage: str) -> dict[str, float]:
    from baselines.fourdgs.evaluate import evaluate_cameras

    result = evaluate_cameras(trainer.ctx.model, cameras, stage, trainer.ctx.background, trainer.pipe.backend)
    return {k: float(v) for k, v in result.mean.items() if v is not None and k in ("PSNR", "SSIM")}


def worker(job: dict[str, Any]) -> dict[str, Any]:
    """Train one scene as described by `job`; return the measurements (runs in a fresh process)."""
    import torch

    if job["threads"]:
        torch.set_num_threads(job["threads"])
    from arguments import peek_plugins
    from baselines.fourdgs.app import build_trainer
    from baselines.fourdgs.plugins import register_plugin
    from baselines.render.backends import resolve_backend
    from baselines.render.kernel import kernel_available

    probe_class = register_plugin(_make_probe_class())
    argv = ["-s", job["scene_path"], "-m", job["model_path"], "--configs", job["config"], "--quiet", "--overwrite",
            "--test_iterations", "[]", "--save_iterations", "[]"]
    if job["coarse_iterations"] is not None:
        argv += ["--coarse_iterations", str(job["coarse_iterations"])]
    if job["iterations"] is not None:
        argv += ["--iterations", str(job["iterations"])]
    argv += job["train_args"]
    # The probe joins the plugins the run would load anyway: --plugin flags replace a config's
    # RunParams.plugin, so without flags the config's list is repeated with the probe added.
    requested = peek_plugins(argv)
    flagged = any(a == "--plugin" or a.startswith("--plugin=") for a in argv)
    argv += ["--plugin", probe_class.name if flagged else ",".join([*requested, probe_class.name])]
    trainer = build_trainer(argv)
    probe = next(p for p in trainer.hooks.plugins if p.name == probe_class.name)
    probe.timer = trainer.timer
    trainer.build()
    rss_loaded = _maxrss_bytes()
    initial = _mean_metrics(trainer, trainer.test_cameras, "coarse")
    wall0, cpu0 = time.perf_counter(), time.process_time()
    result = trainer.train()
    train_wall, train_cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    rss_trained = _maxrss_bytes()
    eval_start = time.perf_counter()
    final = _mean_metrics(trainer, trainer.test_cameras, "fine")
    eval_s = time.perf_counter() - eval_start
    train_fit = _mean_metrics(trainer, trainer.train_cameras, "fine")
    kernel_ok, kernel_info = kernel_available()
    backend = resolve_backend(trainer.pipe.backend, trainer.device).name
    cam = trainer.train_cameras[0]
    return {
        "scene": job["scene"], "width": cam.width, "height": cam.height,
        "train_views": len(trainer.train_cameras), "test_views": len(trainer.test_cameras),
        "threads": torch.get_num_threads(), "torch": torch.__version__,
        "backend": backend, "kernel": kernel_info if kernel_ok else f"unavailable: {kernel_info}",
        "coarse_iterations": trainer.opt.coarse_iterations, "iterations": trainer.opt.iterations,
        "plugins": [p.name for p in trainer.hooks.plugins],
        "point_cloud_source": trainer.ctx.point_cloud_source,
        "stages": probe.stages, "train_wall_s": train_wall, "train_cpu_s": train_cpu,
        "timings_ms_all": result.timings, "final_gaussians": result.num_gaussians,
        "peak_gaussians": probe.peak_gaussians, "rss_loaded_bytes": rss_loaded,
        "rss_trained_bytes": rss_trained, "rss_peak_bytes": _maxrss_bytes(),
        "test_initial": initial, "test_final": final, "train_final": train_fit, "eval_s": eval_s,
    }


def deformation_worker(payload: str) -> None:
    """benchmarks/deformation.py's comparison, imported (not copied), in this process."""
    import importlib.util

    import torch

    spec = importlib.util.spec_from_file_location("bench_deformation", REPO_ROOT / "benchmarks" / "deformation.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    parsed = json.loads(payload)
    if parsed["threads"]:
        torch.set_num_threads(parsed["threads"])
    module.run(list(module.CONFIGS), parsed["sizes"], parsed["repeats"], parsed["warmup"])


# ------------------------------------------------------------------------------ parent side
def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    apply_thread_policy(env, torch_loaded=False)  # the child starts torch afresh; the user's settings win
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def run_scene(job: dict[str, Any]) -> dict[str, Any]:
    """Run `worker(job)` in a fresh interpreter; return its measurements (or an error record)."""
    with tempfile.TemporaryDirectory(prefix="train_baseline_") as tmp:
        out = Path(tmp) / "result.json"
        job = {**job, "model_path": job["model_path"] or str(Path(tmp) / "model")}
        cmd = [sys.executable, str(Path(__file__).resolve()), "--_worker", json.dumps(job), "--_out", str(out)]
        start = time.perf_counter()
        proc = subprocess.run(cmd, env=_child_env(), cwd=REPO_ROOT, capture_output=True, text=True)
        if proc.returncode != 0 or not out.is_file():
            tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-15:])
            return {"scene": job["scene"], "error": f"worker exited with {proc.returncode}:\n{tail}"}
        record = json.loads(out.read_text())
        record["process_wall_s"] = time.perf_counter() - start
        return record


def _mib(value: int) -> str:
    return f"{value / 2**20:.0f}"


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def summary_table(records: list[dict[str, Any]]) -> list[str]:
    lines = [
        "| scene | views train/test | coarse it/s | fine it/s | train wall s | CPU ms/it coarse / fine "
        "| peak RSS MiB (after load) | Gaussians final (peak) | test PSNR init -> final | test SSIM final "
        "| train PSNR final |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in records:
        if "error" in r:
            lines.append(f"| {r['scene']} | failed: {r['error'].splitlines()[0]} |" + " |" * 9)
            continue
        c, f = r["stages"].get("coarse", {}), r["stages"].get("fine", {})
        lines.append(
            f"| {r['scene']} | {r['train_views']}/{r['test_views']} | {_fmt(c.get('it_per_s'))} "
            f"| {_fmt(f.get('it_per_s'))} | {r['train_wall_s']:.1f} "
            f"| {_fmt(c.get('cpu_ms_per_it'), 0)} / {_fmt(f.get('cpu_ms_per_it'), 0)} "
            f"| {_mib(r['rss_peak_bytes'])} ({_mib(r['rss_loaded_bytes'])}) "
            f"| {r['final_gaussians']} ({r['peak_gaussians']}) "
            f"| {_fmt(r['test_initial'].get('PSNR'))} -> {_fmt(r['test_final'].get('PSNR'))} "
            f"| {_fmt(r['test_final'].get('SSIM'), 4)} | {_fmt(r['train_final'].get('PSNR'))} |"
        )
    return lines


def phase_table(records: list[dict[str, Any]], stage: str) -> list[str]:
    """Median ms per phase and per whole iteration (the iteration's median, from hook to hook)."""
    head = " | ".join(PHASE_LABELS[p] for p in PHASES)
    lines = [f"| scene | {head} | other | iteration (median) | mean ms/it |", "|---|" + "---:|" * (len(PHASES) + 3)]
    for r in records:
        s = r.get("stages", {}).get(stage)
        if not s or "phases_median_ms" not in s:
            continue
        medians = s["phases_median_ms"]
        total = medians.get("iteration", s["ms_per_it"])
        cells = []
        for p in PHASES:
            ms = medians.get(p, 0.0)
            cells.append(f"{ms:.1f} ({100 * ms / total:.0f}%)")
        other = total - sum(medians.get(p, 0.0) for p in PHASES)
        cells.append(f"{other:.1f} ({100 * other / total:.0f}%)")
        lines.append(f"| {r['scene']} | " + " | ".join(cells) + f" | {total:.1f} | {s['ms_per_it']:.1f} |")
    return lines


def describe_schedule(args: argparse.Namespace, first: dict[str, Any], coarse: int | None, fine: int | None) -> str:
    lengths = f"coarse {first.get('coarse_iterations', coarse)} + fine {first.get('iterations', fine)} iterations"
    if args.full and args.iterations is None and args.coarse_iterations is None:
        return lengths + " (the config's schedule, --full)"
    return lengths + " (SHORT schedule: the config's stage lengths overridden, the rest of the config unchanged)"


def report_lines(args: argparse.Namespace, records: list[dict[str, Any]], schedule: str,
                 load_start: str, load_end: str) -> list[str]:
    """The markdown report: header, summary table, per-stage phase tables."""
    first = next((r for r in records if "error" not in r), {})
    config = args.config.resolve()
    config_name = config.relative_to(REPO_ROOT) if config.is_relative_to(REPO_ROOT) else config
    kernel = str(first.get("kernel", "?"))
    lines = [
        f"## 4DGS baseline on the synthetic suite ({first.get('width', '?')}x{first.get('height', '?')} images)",
        "",
        f"- config: {config_name}, {schedule}; extra flags: {args.train_args or 'none'}",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical cores; torch {first.get('torch', '?')}, "
        f"{first.get('threads', '?')} threads, backend {first.get('backend', '?')} (compiled kernel: "
        f"{kernel if kernel.startswith('unavailable') else 'yes'}), baselines/thread_policy.py's OpenMP and "
        "allocator policy; "
        "one fresh process per scene",
        f"- load average (1/5/15 min): {load_start} at start, {load_end} at end",
        "- it/s = iterations / stage wall time; CPU = process CPU time of all threads; peak RSS = ru_maxrss of the "
        "run's process (tracemalloc does not see torch tensors); PSNR/SSIM on the held-out views (every 8th frame), "
        "'init' = the initial point cloud before training",
        "",
        *summary_table(records),
    ]
    for stage in ("fine", "coarse"):
        lines += ["", f"Where a {stage}-stage iteration's time goes (median ms per iteration and share of the median "
                  "iteration; 'other' = the median iteration minus the phases' medians; the mean includes "
                  "densification steps and the end-of-stage save; loss+backward holds the whole backward pass):",
                  "", *phase_table(records, stage)]
    return lines


def parse_size(text: str) -> tuple[int, int]:
    from baselines.synthetic.__main__ import parse_size as parse

    return parse(text)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default=",".join(DEFAULT_SCENES), help="comma-separated scene names")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="train.py --configs file")
    parser.add_argument("--iterations", type=int,
                        help=f"fine-stage iterations (default {SHORT_FINE}; config's with --full)")
    parser.add_argument("--coarse_iterations", type=int,
                        help=f"coarse-stage iterations (default {SHORT_COARSE}; config's with --full)")
    parser.add_argument("--full", action="store_true", help="the config's own schedule (slow on a laptop CPU)")
    parser.add_argument("--size", help="image size WxH (default: the simulator's, 128x96)")
    parser.add_argument("--threads", type=int, help="torch threads in each run (default: torch's)")
    parser.add_argument("--data_root", type=Path, default=REPO_ROOT / "data" / "synthetic",
                        help="scene cache folder")
    parser.add_argument("--keep_outputs", type=Path, help="keep each run's model folder under DIR/<scene>")
    parser.add_argument("--train_args", default="", help="extra train.py flags, e.g. \"--batch_size 2\"")
    parser.add_argument("--json", type=Path, help="also write all measurements to this JSON file")
    parser.add_argument("--deformation", action="store_true",
                        help="also run benchmarks/deformation.py's comparison (fresh process)")
    parser.add_argument("--deformation_sizes", type=int, nargs="+", default=[20_000, 100_000])
    parser.add_argument("--deformation_repeats", type=int, default=9)
    parser.add_argument("--_worker", help=argparse.SUPPRESS)
    parser.add_argument("--_out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--_deformation_worker", help=argparse.SUPPRESS)
    return parser


def _write_json_atomic(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args._worker:
        _write_json_atomic(args._out, worker(json.loads(args._worker)))
        return 0
    if args._deformation_worker:
        deformation_worker(args._deformation_worker)
        return 0

    # Every input check before the first (long) run.
    from baselines.synthetic import list_scenes

    names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    unknown = [n for n in names if n not in list_scenes()]
    if unknown or not names:
        raise SystemExit(f"error: unknown scene(s) {unknown}; available: {', '.join(list_scenes())}")
    if not args.config.is_file():
        raise SystemExit(f"error: --config {args.config}: no such file")
    for flag in ("iterations", "coarse_iterations", "threads"):
        value = getattr(args, flag)
        if value is not None and value < (1 if flag == "threads" else 0):
            raise SystemExit(f"error: --{flag} must be {'positive' if flag == 'threads' else '>= 0'}, got {value}")
    try:
        size = parse_size(args.size) if args.size else None
    except ValueError as exc:
        raise SystemExit(f"error: {exc}") from None
    coarse = args.coarse_iterations if args.coarse_iterations is not None else (None if args.full else SHORT_COARSE)
    fine = args.iterations if args.iterations is not None else (None if args.full else SHORT_FINE)

    load_start = load_average()
    paths = {name: ensure_scene(args.data_root, name, size)[0] for name in names}
    records = []
    for name in names:
        job = {"scene": name, "scene_path": str(paths[name]), "config": str(args.config.resolve()),
               "coarse_iterations": coarse, "iterations": fine, "threads": args.threads,
               "train_args": shlex.split(args.train_args),
               "model_path": str(args.keep_outputs / name) if args.keep_outputs else None}
        print(f"[bench] training {name} ...", file=sys.stderr, flush=True)
        record = run_scene(job)
        if "error" in record:
            print(f"[bench] {name}: {record['error']}", file=sys.stderr)
        else:
            print(f"[bench] {name}: {record['train_wall_s']:.0f} s, {record['final_gaussians']} Gaussians, "
                  f"test PSNR {record['test_final'].get('PSNR', float('nan')):.2f}", file=sys.stderr, flush=True)
        records.append(record)
    load_end = load_average()

    ok = [r for r in records if "error" not in r]
    schedule = describe_schedule(args, ok[0] if ok else {}, coarse, fine)
    print("\n".join(report_lines(args, records, schedule, load_start, load_end)))
    if args.json:
        _write_json_atomic(args.json, {"load_average_start": load_start, "load_average_end": load_end,
                                       "schedule": schedule, "cpu": cpu_model(), "runs": records})
    if args.deformation:
        print("\n## Deformation module, ours vs 4DGS's recipe (benchmarks/deformation.py)\n")
        payload = json.dumps({"sizes": args.deformation_sizes, "repeats": args.deformation_repeats,
                              "warmup": 2, "threads": args.threads})
        sys.stdout.flush()
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--_deformation_worker", payload],
                              env=_child_env(), cwd=REPO_ROOT)
        if proc.returncode != 0:
            return proc.returncode
        print(f"\n- load average after: {load_average()}")
    return 1 if len(ok) < len(records) else 0


if __name__ == "__main__":
    sys.exit(main())
