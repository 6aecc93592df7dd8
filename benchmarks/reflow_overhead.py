"""What ReFlow costs, next to the 4DGS baseline, measured in ONE run: the whole run and one iteration.

    python benchmarks/reflow_overhead.py [--scene skating] [--size WxH] [--whole-iterations 2000] [--iterations 30]

Whole run (first table): `train.py` for each variant of WHOLE_VARIANTS, back to back in fresh
processes and fresh folders (nothing cached: the canonical space is built), the same schedule
(`--coarse-iterations`, `--whole-iterations`; the synthetic config's 300 + 2000 by default), timed
phase by phase by benchmarks/whole_run.py (canonical space, training with its pieces: partner
projection, flow channels, flow maps + losses, the dynamic deformation, the densification pass;
evaluation), with the ratio ReFlow / baseline per phase. `--whole-variants` adds rows (e.g.
`reflow_both`, the paper's pairwise batch).

One iteration (second table): every variant trains the same scene from the SAME Gaussians
(ReFlow's initial cloud: the host's triangulated points plus the seeded dynamic points), with
densification off so the count stays fixed; the variants' iterations are interleaved (A, B, C,
A, B, C, ...) so that a busy machine slows all of them alike. Printed per variant: median ms per
iteration and per host phase (deform+project, rasterize, loss+backward, densify+step), the ratio
to the baseline, and ReFlow's own pieces (flow channels, flow maps and losses forward, the extra
backward pass for 4DGS's densification statistic). Peak RSS comes from one fresh process per
variant (ru_maxrss after the same number of iterations). Prints figures; asserts nothing.
"""
from __future__ import annotations

import argparse
import os
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()  # before torch: OpenMP waits, threads, allocator (baselines/thread_policy.py)

import torch  # noqa: E402

VARIANTS = {
    "baseline": [],
    "reflow": ["--plugin", "reflow"],
    "reflow separation only": ["--plugin", "reflow", "--disable", "full_flow,cam_flow"],
    "reflow full flow only": ["--plugin", "reflow", "--disable", "cam_flow"],
    "reflow camera flow only": ["--plugin", "reflow", "--disable", "full_flow"],
    "baseline batch 2": ["--batch_size", "2"],
    "reflow pair_mode both": ["--plugin", "reflow", "--pair_mode", "both"],
    "reflow 4 keyframes": ["--plugin", "reflow", "--dynamic_keyframes", "4"],
    "reflow no blur": ["--plugin", "reflow", "--flow_blur_sigmas", "[]"],
    "reflow flow_every 2": ["--plugin", "reflow", "--flow_every", "2"],
    # the densification window on (no densification event in these few iterations): its extra pass
    "reflow + densification pass": ["--plugin", "reflow", "--densify_until_iter", "100000",
                                    "--densify_from_iter", "100000"],
}
WHOLE_VARIANTS = {
    "baseline": [],
    "reflow": ["--plugin", "reflow"],
    "reflow_both": ["--plugin", "reflow", "--pair_mode", "both"],
    "baseline_batch2": ["--batch_size", "2"],
    "reflow_fe2": ["--plugin", "reflow", "--flow_every", "2"],
    "reflow_no_comp_init": ["--plugin", "reflow", "--disable", "comp_init"],
    # smaller initial clouds: the one-iteration table shows the per-Gaussian cost near the baseline's,
    # so the whole run's ratio is mostly the initial count
    "reflow_static_5k": ["--plugin", "reflow", "--canonical_max_points", "5000"],
    "reflow_static_5k_seeds_5k": ["--plugin", "reflow", "--canonical_max_points", "5000", "--seed_points", "5000"],
    "reflow_static_2k": ["--plugin", "reflow", "--canonical_max_points", "2000"],
}
WHOLE_PHASES = ("load", "setup", "masks+canonical", "training steps", "partner projection", "flow channels",
                "flow maps+losses", "dynamic deformation", "densification pass", "test events", "flow evaluation",
                "final evaluation", "total")
PHASES = ("deform_project", "rasterize", "loss_backward", "densify_step")
TRAIN_FLAGS: list[str] = []  # --train-flags: added to every variant's train.py flags (e.g. the GPU backend)


def scene_path(name: str, size: str = "") -> Path:
    """data/synthetic/NAME (generated if missing); with `size` ("WxH") NAME_WxH at that size."""
    from baselines.synthetic import get_scene, simulate

    path = REPO / "data" / "synthetic" / (f"{name}_{size}" if size else name)
    if not (path / "poses_bounds.npy").is_file():
        overrides = {}
        if size:
            width, height = (int(v) for v in size.lower().split("x"))
            overrides = {"width": width, "height": height}
        simulate(get_scene(name, **overrides), path, progress=False)
    return path


def build(variant: str, scene: Path, out: Path):
    """A trainer at the start of the fine stage, densification off."""
    from baselines.fourdgs.app import build_trainer

    argv = ["-s", str(scene), "-m", str(out / variant.replace(" ", "_").replace(":", "")),
            "--configs", str(REPO / "arguments" / "synthetic" / "default.py"), "--quiet", "--overwrite",
            "--densify_until_iter", "0", "--test_iterations", "[]", "--save_iterations", "[]", *VARIANTS[variant],
            *TRAIN_FLAGS]
    if "--plugin" in argv:
        argv += ["--flow_vis_every", "0"]
    trainer = build_trainer(argv)
    shared, own = out / "canonical_cache", Path(argv[3]) / "reflow" / "canonical"
    if shared.is_dir() and not own.is_dir():  # one canonical space for every variant (its cache key checks it)
        shutil.copytree(shared, own)
    trainer.build()
    if own.is_dir() and not shared.is_dir():
        shutil.copytree(own, shared)
    return trainer


def same_gaussians(trainers: dict) -> None:
    """Give every baseline variant ReFlow's initial Gaussians (same count, same positions and colours)."""
    from baselines.fourdgs.gaussian_model import GaussianModel

    source = trainers["reflow"].ctx.model
    for name in [n for n in trainers if n.startswith("baseline")]:
        base = trainers[name]
        model = GaussianModel(base.args.model.sh_degree, base.hidden)
        xyz = source.get_xyz.detach().clone()
        model.create_from_pcd(xyz, torch.full_like(xyz, 0.5), base.cameras_extent)
        with torch.no_grad():
            for field in ("_xyz", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity"):
                getattr(model, field).copy_(getattr(source, field))
        base.ctx.model = model


class PieceTimer:
    """Wall time of ReFlow's own functions (wrapped in place), per iteration."""

    def __init__(self) -> None:
        self.current: dict[str, float] = {}

    def wrap(self, module, name: str, label: str) -> None:
        inner = getattr(module, name)

        def timed(*args, **kwargs):
            start = time.perf_counter()
            result = inner(*args, **kwargs)
            self.current[label] = self.current.get(label, 0.0) + time.perf_counter() - start
            return result

        setattr(module, name, timed)


def run_interleaved(trainers: dict, iterations: int, warmup: int) -> dict:
    import reflow_plugin.plugin as plugin_module
    from baselines.fourdgs import trainer as trainer_module

    pieces = PieceTimer()
    pieces.wrap(plugin_module, "flow_features", "flow channels")
    pieces.wrap(plugin_module, "flow_losses", "flow maps + losses (forward)")
    extra_grad = trainer_module.Trainer._baseline_screen_grads

    def timed_grads(self, baseline):
        start = time.perf_counter()
        result = extra_grad(self, baseline)
        pieces.current["densification statistic pass"] = pieces.current.get("densification statistic pass", 0.0) + (
            time.perf_counter() - start)
        return result

    trainer_module.Trainer._baseline_screen_grads = timed_grads
    for trainer in trainers.values():
        trainer._begin_stage("fine", warmup + iterations)
    samples = {name: {"total": [], "cpu": [], **{p: [] for p in PHASES}, "pieces": []} for name in trainers}
    for step in range(1, warmup + iterations + 1):
        for name, trainer in trainers.items():
            before = dict(trainer.timer.total)
            pieces.current = {}
            trainer.ctx.iteration = step
            start, cpu = time.perf_counter(), time.process_time()
            trainer.train_step()
            elapsed = time.perf_counter() - start
            if step > warmup:
                samples[name]["total"].append(elapsed)
                samples[name]["cpu"].append(time.process_time() - cpu)
                for phase in PHASES:
                    samples[name][phase].append(trainer.timer.total[phase] - before.get(phase, 0.0))
                samples[name]["pieces"].append(dict(pieces.current))
    return samples


def peak_rss(variant: str, scene: Path, out: Path, iterations: int) -> float:
    """ru_maxrss (MiB) of a fresh process that trains `iterations` fine steps of `variant`."""
    code = (
        "import sys, resource; sys.path.insert(0, %r); from benchmarks.reflow_overhead import build;"
        "from pathlib import Path; t = build(%r, Path(%r), Path(%r)); t._begin_stage('fine', %d)\n"
        "for i in range(1, %d): t.ctx.iteration = i; t.train_step()\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"
    ) % (str(REPO), variant, str(scene), str(out / "rss"), iterations + 1, iterations + 1)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    if result.returncode != 0:
        return float("nan")
    return float(result.stdout.strip().splitlines()[-1])


def whole_run(variant: str, scene: Path, out: Path, coarse: int, fine: int) -> dict:
    """benchmarks/whole_run.py's phase times of one fresh train.py run of `variant`."""
    import json
    import shutil

    run_dir = out / "whole" / variant
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    argv = ["-s", str(scene), "-m", str(run_dir), "--configs", str(REPO / "arguments" / "synthetic" / "default.py"),
            "--quiet", "--coarse_iterations", str(coarse), "--iterations", str(fine),
            "--position_lr_max_steps", str(fine), "--densify_until_iter", str(int(0.75 * fine)),
            "--test_iterations", str(fine), "--save_iterations", str(fine), *WHOLE_VARIANTS[variant], *TRAIN_FLAGS]
    if "--plugin" in argv:
        argv += ["--flow_vis_every", "0"]
    report = out / "whole" / f"{variant}.json"
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "whole_run.py"), str(report), "--", *argv],
                   cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    return json.loads(report.read_text())


def print_whole(results: dict, scene: str, coarse: int, fine: int) -> None:
    names = list(results)
    print(f"# whole run, {scene}, {coarse} coarse + {fine} fine iterations, one fresh process per variant, back to "
          f"back; load average {os.getloadavg()[0]:.2f}; wall seconds (CPU seconds)")
    print("| phase | " + " | ".join(names) + " | " + " | ".join(f"{n} / baseline" for n in names[1:]) + " |")
    print("|---|" + "---:|" * (2 * len(names) - 1))
    for phase in WHOLE_PHASES:
        cells = []
        for name in names:
            wall, cpu = results[name]["phases"].get(phase, [0.0, 0.0])
            cells.append(f"{wall:.1f} ({cpu:.1f})" if wall else "-")
        base = results["baseline"]["phases"].get(phase, [0.0, 0.0])[0]
        ratios = [f"{results[n]['phases'].get(phase, [0.0])[0] / base:.2f}x" if base > 0 else "-" for n in names[1:]]
        print(f"| {phase} | " + " | ".join(cells) + " | " + " | ".join(ratios) + " |")
    def quality(r: dict) -> str:  # a scene without moving pixels has no PSNR-dynamic
        if r.get("psnr") is None:
            return "-"
        return f"{r['psnr']:.2f}" + (f" / {r['psnr_dynamic']:.2f}" if r.get("psnr_dynamic") is not None else " / -")

    print("| test PSNR / PSNR-dynamic | " + " | ".join(quality(r) for r in results.values())
          + " |" + " |" * (len(names) - 1))
    print("| Gaussians at the end | " + " | ".join(str(r["gaussians"]) for r in results.values()) + " |"
          + " |" * (len(names) - 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="skating", help="synthetic scene name (generated if missing)")
    parser.add_argument("--size", default="", help="WxH: the scene generated at this size (data/synthetic/NAME_WxH); "
                                                   "default: the scene's own (the embedded scene: 128x96)")
    parser.add_argument("--iterations", type=int, default=30, help="timed iterations per variant")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--out", default=str(REPO / "output" / "bench_reflow_overhead"))
    parser.add_argument("--no-rss", action="store_true", help="skip the peak-RSS subprocesses")
    parser.add_argument("--coarse-iterations", type=int, default=300, help="whole run: coarse iterations")
    parser.add_argument("--whole-iterations", type=int, default=2000, help="whole run: fine iterations (0 = skip)")
    parser.add_argument("--whole-variants", default="baseline,reflow",
                        help=f"whole run: comma-separated, from {', '.join(WHOLE_VARIANTS)} (baseline first)")
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help="one-iteration table: comma-separated variants (baseline and reflow always)")
    parser.add_argument("--train-flags", default="",
                        help="train.py flags added to every variant, e.g. '--device cuda --backend gsplat'")
    args = parser.parse_args()
    TRAIN_FLAGS.extend(shlex.split(args.train_flags))
    import logging

    logging.basicConfig(level=logging.WARNING)
    scene, out = scene_path(args.scene, args.size), Path(args.out)
    if args.whole_iterations > 0:
        names = [n for n in args.whole_variants.split(",") if n]
        unknown = [n for n in names if n not in WHOLE_VARIANTS]
        if unknown or not names or names[0] != "baseline":
            parser.error(f"--whole-variants: baseline first, then any of {list(WHOLE_VARIANTS)}; got {names}")
        results = {}
        for name in names:  # each variant's total as it ends: a later crash keeps the earlier figures
            results[name] = whole_run(name, scene, out, args.coarse_iterations, args.whole_iterations)
            print(f"[whole run] {name}: {results[name]['phases']['total'][0]:.1f} s wall, test PSNR "
                  f"{results[name].get('psnr')}", flush=True)
        print_whole(results, f"{args.scene} {args.size}".strip(), args.coarse_iterations, args.whole_iterations)
        print()
    if args.iterations <= 0:
        return
    chosen = ["baseline", "reflow"] + [v for v in args.variants.split(",") if v in VARIANTS and v not in ("baseline", "reflow")]
    for name in [v for v in list(VARIANTS) if v not in chosen]:
        VARIANTS.pop(name)
    trainers = {name: build(name, scene, out) for name in VARIANTS}
    same_gaussians(trainers)
    n = trainers["reflow"].ctx.model.num_gaussians
    dynamic = int(trainers["reflow"].ctx.model.deformation_table.sum())
    samples = run_interleaved(trainers, args.iterations, args.warmup)
    base = statistics.median(samples["baseline"]["total"])
    load = os.getloadavg()[0]
    print(f"# one iteration, {args.scene}: {n} Gaussians ({dynamic} dynamic), {args.iterations} interleaved "
          f"iterations per variant after {args.warmup} warm-up; torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, load average {load:.2f}")
    base_cpu = statistics.median(samples["baseline"]["cpu"])
    print("| variant | ms/iteration (median) | vs baseline | CPU ms/iteration | vs baseline (CPU) | deform+project | "
          "rasterize | loss+backward | densify+step | peak RSS MiB |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in VARIANTS:
        s = samples[name]
        rss = float("nan") if args.no_rss else peak_rss(name, scene, out, 10)
        cells = " | ".join(f"{1000 * statistics.median(s[p]):.1f}" for p in PHASES)
        total = statistics.median(s["total"])
        cpu = statistics.median(s["cpu"])
        print(f"| {name} | {1000 * total:.1f} | {total / base:.2f}x | {1000 * cpu:.1f} | {cpu / base_cpu:.2f}x | {cells} "
              f"| {rss:.0f} |")
    print("\nReFlow's own pieces inside those phases (median ms per iteration, full variant):")
    pieces = samples["reflow"]["pieces"]
    for key in sorted({k for p in pieces for k in p}):
        print(f"  {key}: {1000 * statistics.median([p.get(key, 0.0) for p in pieces]):.1f}")


if __name__ == "__main__":
    main()
