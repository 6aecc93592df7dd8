"""Baseline vs ReFlow on the synthetic suite: test PSNR/SSIM, dynamic-region PSNR, flow EPE, time.

    python benchmarks/reflow_suite.py [--scenes balloon,playground,skating,truck,umbrella]
                                      [--out output/suite] [--jobs 1] [-- extra train.py flags]
    python benchmarks/reflow_suite.py --priors real --schedule half --jobs 2 \
        --methods baseline,reflow,reflow_no_align           # the suite as real captures come

Each (scene, method) is an ordinary `train.py` run in `OUT/<scene>/<method>` with the scene's
synthetic config (`arguments/synthetic/default.py`, ReFlow: `arguments/synthetic/reflow.py`), the
full schedule; `reflow_no_comp_init` is ReFlow without its complete canonical space (part 1
alone). `--methods` defaults to `baseline,reflow`. A run whose `results.json` holds its final metrics is
reused (a killed sweep resumes) when its `run.json` records the same train.py command; a run trained
with another schedule or other flags, or a `--priors real` scene written at another `--scene_scale`,
stops the suite with one error line (another `--out`, or `--report_only` to read the runs as they
are). The baseline's
flow is measured afterwards with `python -m reflow_plugin.evaluate` (the same renderer ReFlow's
own evaluation uses). Prints one Markdown table (per scene and mean) and writes it with the raw
figures to `OUT/suite.md` / `OUT/suite.json`. `--jobs 2` runs two trainings at once with one
thread each (about as fast in total on 2 cores, and the wall-clock column is then not comparable
with a quiet single run).

`--priors real` trains on the scenes written as real captures come (`python -m baselines.synthetic
--priors real --scene_scale 50`: monocular disparity with a per-frame scale and shift, NVIDIA-like
world units, no motion masks, so ReFlow estimates them), in `data/synthetic_real/<scene>` and
`output/suite_real/` by default; PSNR-dynamic still uses the exact masks (gt/motion_masks).
`reflow_no_align` is the paper's "w/o align" (`--no-canonical_align`; on monocular disparity
the raw cloud fails the initial-cloud check and the run falls back to the per-frame fits),
`reflow_no_align_unchecked` the raw cloud kept (`--no-canonical_check`). Variants measured and
dropped (capped dynamic rates, promotion, relabelling, wider mask pairings) are in
docs/PARAMETERS.md with their figures. `--schedule half` is the
ablation's half schedule (300 coarse + 1000 fine iterations, decay and densification scaled),
`quarter` half of that again (150 + 500). `--report_only` trains nothing and prints the table of
the finished runs.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENES = ("balloon", "playground", "skating", "truck", "umbrella")
METHODS = {
    "baseline": ["--configs", "arguments/synthetic/default.py"],
    "reflow": ["--configs", "arguments/synthetic/reflow.py", "--plugin", "reflow"],
    # the deformation MLP in float32 (4DGS's arithmetic) where `auto` picks bfloat16 (CPUs with it natively)
    "baseline_fp32": ["--configs", "arguments/synthetic/default.py", "--mlp_precision", "float32"],
    "reflow_fp32": ["--configs", "arguments/synthetic/reflow.py", "--plugin", "reflow", "--mlp_precision", "float32"],
    # part 1 alone: the host's triangulated cloud plus keyframe seeds instead of the canonical space
    "reflow_no_comp_init": ["--configs", "arguments/synthetic/reflow.py", "--plugin", "reflow", "--disable", "comp_init"],
    # the paper's "w/o align": raw per-frame pointmaps (the initial-cloud check may fall back)
    "reflow_no_align": ["--configs", "arguments/synthetic/reflow.py", "--plugin", "reflow", "--no-canonical_align"],
    # the same without the check's fallback: the raw pointmaps whatever their scale
    "reflow_no_align_unchecked": ["--configs", "arguments/synthetic/reflow.py", "--plugin", "reflow",
                                  "--no-canonical_align", "--no-canonical_check"],
    # static Gaussians through a whole-scene 4DGS field of their own (`--static_decoder field`, the
    # default since 2026-11-28: the same runs as `reflow`, kept so that older output folders still read)
    "reflow_static_field": ["--configs", "arguments/synthetic/reflow.py", "--plugin", "reflow",
                            "--static_decoder", "field"],
    # the paper's rigid static scene, the default until 2026-11-28 (cheaper: no network for static Gaussians)
    "reflow_static_none": ["--configs", "arguments/synthetic/reflow.py", "--plugin", "reflow",
                           "--static_decoder", "none"],
}
SCHEDULES = {
    "full": [],
    "half": ["--iterations", "1000", "--position_lr_max_steps", "1000", "--densify_until_iter", "750",
             "--test_iterations", "500", "1000", "--save_iterations", "1000"],
    "quarter": ["--coarse_iterations", "150", "--iterations", "500", "--position_lr_max_steps", "500",
                "--densify_until_iter", "375", "--test_iterations", "250", "500", "--save_iterations", "500"],
}
PRIORS = {"exact": ("synthetic", []), "real": ("synthetic_real", ["--priors", "real", "--scene_scale"])}


def _latest(results: dict) -> tuple[str, dict]:
    key = max((k for k in results if k.startswith("ours_")), key=lambda k: int(k.split("_")[1]))
    return key, results[key]


def finished(run: Path) -> bool:
    """Whether the run wrote its final metrics (a plugin writes results.json early, at set-up)."""
    path = run / "results.json"
    return path.is_file() and any(k.startswith("ours_") for k in json.loads(path.read_text()))


def scene_source(scene: str, priors: str = "exact", scene_scale: float = 50.0) -> tuple[Path, list[str]]:
    """(data folder, simulator flags) of a suite scene in the given priors mode."""
    folder, flags = PRIORS[priors]
    return ROOT / "data" / folder / scene, (flags + [str(scene_scale)] if flags else [])


class SuiteError(RuntimeError):
    """A scene folder or run folder holds something other than what this command asks for."""


def check_scene_data(source: Path, priors: str, scene_scale: float) -> None:
    """An existing `--priors real` scene must have been written at `scene_scale` (it is reused, not rewritten)."""
    if priors != "real" or not (source / "scene.json").is_file():
        return
    written = json.loads((source / "scene.json").read_text()).get("scene_scale")
    if written is None or abs(float(written) - scene_scale) > 1e-9 * max(1.0, scene_scale):
        raise SuiteError(f"{source} was written with --scene_scale {written}, not {scene_scale:g}: delete the "
                         "folder to write it again, or pass its scale")


def check_run_command(run: Path, command: list[str]) -> None:
    """A finished run is reused only when it was trained with `command` (train.py and its flags)."""
    record = run / "run.json"
    stored = json.loads(record.read_text()).get("command") if record.is_file() else None
    if stored != command:
        shown = " ".join(stored) if stored else "no command recorded"
        raise SuiteError(f"{run} was trained with another command ({shown}); use another --out for this "
                         "schedule or these flags, or --report_only to read the finished runs as they are")


def run_one(scene: str, method: str, out: Path, extra: list[str], threads: int | None, priors: str = "exact",
            scene_scale: float = 50.0, reuse_any: bool = False) -> Path:
    """Train (unless done) and measure the flow of one (scene, method); returns the run folder.

    A finished run is reused when it was trained with the same command (else SuiteError); with
    `reuse_any` (--report_only) whatever command it had.
    """
    run = out / scene / method
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    source, flags = scene_source(scene, priors, scene_scale)
    cmd = [sys.executable, "train.py", "-s", str(source), "-m", str(run), "--quiet", "--overwrite", *METHODS[method],
           *extra]
    if finished(run) and not reuse_any:
        check_run_command(run, cmd[1:])
    if not finished(run):
        check_scene_data(source, priors, scene_scale)
        if not (source / "poses_bounds.npy").is_file():
            subprocess.run([sys.executable, "-m", "baselines.synthetic", "--scene", scene, "--out", str(source), "--quiet",
                            *flags], cwd=ROOT, check=True, env=env)
        # no results.json: never trained, or a torn run (killed): --overwrite clears the latter's files
        run.mkdir(parents=True, exist_ok=True)
        with open(run / "suite_train.log", "w") as log:
            subprocess.run(cmd, cwd=ROOT, check=True, env=env, stdout=log, stderr=subprocess.STDOUT)
    method_key, _ = _latest(json.loads((run / "results.json").read_text()))
    flow_file = run / "flow_metrics.json"
    if not flow_file.is_file() or method_key not in json.loads(flow_file.read_text()):
        subprocess.run([sys.executable, "-m", "reflow_plugin.evaluate", "-m", str(run)], cwd=ROOT, check=True, env=env,
                       stdout=subprocess.DEVNULL)
    return run


def summarise(run: Path) -> dict:
    """The figures of one finished run."""
    key, metrics = _latest(json.loads((run / "results.json").read_text()))
    flow = json.loads((run / "flow_metrics.json").read_text()).get(key, {})
    log = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    end = [r for r in log if r["kind"] == "train_end"]
    results = json.loads((run / "results.json").read_text())
    check = results.get("reflow", {}).get("canonical_check", {})
    row = {"PSNR": metrics["PSNR"], "SSIM": metrics["SSIM"], "PSNR-dynamic": metrics.get("PSNR-dynamic"),
           "PSNR-static": metrics.get("PSNR-static"), "train_s": end[-1]["wall_seconds"] if end else None,
           "initial cloud": check.get("used")}
    if flow.get("available"):
        row.update({"EPE-train": flow["train"]["epe"], "EPE-train-dynamic": flow["train"]["epe_dynamic"],
                    "EPE-test": flow["test"]["epe"], "EPE-test-dynamic": flow["test"]["epe_dynamic"]})
    return row


COLUMNS = ("PSNR", "SSIM", "PSNR-dynamic", "PSNR-static", "EPE-train", "EPE-train-dynamic", "EPE-test",
           "EPE-test-dynamic", "train_s", "initial cloud")


def table(rows: dict[str, dict[str, dict]]) -> str:
    """Markdown: one line per (scene, method), then the mean per method."""
    fmt = {"SSIM": "{:.3f}", "train_s": "{:.0f}"}
    lines = ["| scene | method | " + " | ".join(COLUMNS) + " |", "|" + "---|" * (len(COLUMNS) + 2)]

    def cells(values: dict) -> str:
        return " | ".join("-" if values.get(c) is None else str(values[c]) if isinstance(values[c], str)
                          else fmt.get(c, "{:.2f}").format(values[c]) for c in COLUMNS)

    for scene, methods in rows.items():
        for method, values in methods.items():
            lines.append(f"| {scene} | {method} | {cells(values)} |")
    for method in METHODS:
        got = [m[method] for m in rows.values() if method in m]
        if not got:
            continue
        mean = {c: float(np.mean([g[c] for g in got])) for c in COLUMNS
                if all(isinstance(g.get(c), (int, float)) for g in got)}
        lines.append(f"| **mean** | {method} | {cells(mean)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        extra, argv = argv[argv.index("--") + 1:], argv[:argv.index("--")]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--methods", default="baseline,reflow",
                        help=f"comma list of {', '.join(METHODS)} (default: baseline,reflow)")
    parser.add_argument("--out", type=Path, default=None, help="output/suite (output/suite_real with --priors real)")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--priors", choices=tuple(PRIORS), default="exact",
                        help="real: the scenes as real captures come (see the module docstring)")
    parser.add_argument("--scene_scale", type=float, default=50.0, help="world units of --priors real scenes")
    parser.add_argument("--schedule", choices=tuple(SCHEDULES), default="full")
    parser.add_argument("--report_only", action="store_true", help="train nothing: the table of the finished runs")
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = ROOT / "output" / ("suite" if args.priors == "exact" else "suite_real")
    extra = SCHEDULES[args.schedule] + extra
    scenes, methods = args.scenes.split(","), args.methods.split(",")
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        parser.error(f"unknown method(s) {unknown}; known: {list(METHODS)}")
    threads = max(1, (os.cpu_count() or 1) // args.jobs) if args.jobs > 1 else None
    jobs = [(s, m) for s in scenes for m in methods]
    if args.report_only:
        jobs = [(s, m) for s, m in jobs if finished(args.out / s / m) and (args.out / s / m / "flow_metrics.json").is_file()]
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        try:
            runs = list(pool.map(lambda job: run_one(job[0], job[1], args.out, extra, threads, args.priors,
                                                     args.scene_scale, reuse_any=args.report_only), jobs))
        except SuiteError as error:
            parser.exit(2, f"error: {error}\n")
    rows: dict[str, dict[str, dict]] = {}
    for (scene, method), run in zip(jobs, runs):
        rows.setdefault(scene, {})[method] = summarise(run)
    text = table(rows)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "suite.md").write_text(text + "\n")
    (args.out / "suite.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
