"""What ReFlow costs per fine-stage iteration, next to the 4DGS baseline, measured in ONE run.

    python benchmarks/reflow_overhead.py [--iterations 30] [--scene skating]

Every variant trains the same scene at the same batch size (2 views) from the SAME Gaussians
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
    "baseline": ["--batch_size", "2"],
    "reflow": ["--plugin", "reflow"],
    "reflow: separation only": ["--plugin", "reflow", "--disable", "full_flow,cam_flow", "--batch_size", "2"],
    "reflow: full flow only": ["--plugin", "reflow", "--disable", "cam_flow"],
    "reflow: camera flow only": ["--plugin", "reflow", "--disable", "full_flow"],
}
PHASES = ("deform_project", "rasterize", "loss_backward", "densify_step")


def scene_path(name: str) -> Path:
    from baselines.synthetic import get_scene, simulate

    path = REPO / "data" / "synthetic" / name
    if not (path / "poses_bounds.npy").is_file():
        simulate(get_scene(name), path, progress=False)
    return path


def build(variant: str, scene: Path, out: Path):
    """A trainer at the start of the fine stage, densification off."""
    from baselines.fourdgs.app import build_trainer

    argv = ["-s", str(scene), "-m", str(out / variant.replace(" ", "_").replace(":", "")),
            "--configs", str(REPO / "arguments" / "synthetic" / "default.py"), "--quiet", "--overwrite",
            "--densify_until_iter", "0", "--test_iterations", "[]", "--save_iterations", "[]", *VARIANTS[variant]]
    if "--plugin" in argv:
        argv += ["--flow_vis_every", "0"]
    trainer = build_trainer(argv)
    trainer.build()
    return trainer


def same_gaussians(trainers: dict) -> None:
    """Give the baseline ReFlow's initial Gaussians (same count, same positions and colours)."""
    from baselines.fourdgs.gaussian_model import GaussianModel

    source = trainers["reflow"].ctx.model
    base = trainers["baseline"]
    model = GaussianModel(base.args.model.sh_degree, base.hidden)
    xyz = source.get_xyz.detach().clone()
    model.create_from_pcd(xyz, torch.full_like(xyz, 0.5), base.cameras_extent)
    with torch.no_grad():
        for name in ("_xyz", "_features_dc", "_features_rest", "_scaling", "_rotation", "_opacity"):
            getattr(model, name).copy_(getattr(source, name))
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
    pieces.wrap(plugin_module, "pair_losses", "flow maps + losses (forward)")
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
    samples = {name: {"total": [], **{p: [] for p in PHASES}, "pieces": []} for name in trainers}
    for step in range(1, warmup + iterations + 1):
        for name, trainer in trainers.items():
            before = dict(trainer.timer.total)
            pieces.current = {}
            trainer.ctx.iteration = step
            start = time.perf_counter()
            trainer.train_step()
            elapsed = time.perf_counter() - start
            if step > warmup:
                samples[name]["total"].append(elapsed)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="skating", help="synthetic scene name (generated if missing)")
    parser.add_argument("--iterations", type=int, default=30, help="timed iterations per variant")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--out", default=str(REPO / "output" / "bench_reflow_overhead"))
    parser.add_argument("--no-rss", action="store_true", help="skip the peak-RSS subprocesses")
    args = parser.parse_args()
    import logging

    logging.basicConfig(level=logging.WARNING)
    scene, out = scene_path(args.scene), Path(args.out)
    trainers = {name: build(name, scene, out) for name in VARIANTS}
    same_gaussians(trainers)
    n = trainers["reflow"].ctx.model.num_gaussians
    dynamic = int(trainers["reflow"].ctx.model.deformation_table.sum())
    samples = run_interleaved(trainers, args.iterations, args.warmup)
    base = statistics.median(samples["baseline"]["total"])
    load = os.getloadavg()[0]
    print(f"# {args.scene}: {n} Gaussians ({dynamic} dynamic), batch of 2 views, {args.iterations} interleaved "
          f"iterations per variant after {args.warmup} warm-up; torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, load average {load:.2f}")
    print("| variant | ms/iteration (median) | vs baseline | deform+project | rasterize | loss+backward | densify+step | peak RSS MiB |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in VARIANTS:
        s = samples[name]
        rss = float("nan") if args.no_rss else peak_rss(name, scene, out, 10)
        cells = " | ".join(f"{1000 * statistics.median(s[p]):.1f}" for p in PHASES)
        total = statistics.median(s["total"])
        print(f"| {name} | {1000 * total:.1f} | {total / base:.2f}x | {cells} | {rss:.0f} |")
    print("\nReFlow's own pieces inside those phases (median ms per iteration, full variant):")
    pieces = samples["reflow"]["pieces"]
    for key in sorted({k for p in pieces for k in p}):
        print(f"  {key}: {1000 * statistics.median([p.get(key, 0.0) for p in pieces]):.1f}")


if __name__ == "__main__":
    main()
