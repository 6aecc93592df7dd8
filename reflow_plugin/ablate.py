"""The paper's ablation table (plus the external-flow row), as ordinary train.py runs.

    python -m reflow_plugin.ablate -s data/synthetic/skating -o output/ablation [--rows ...]
                                   [--jobs N] [--executor local|slurm] [-- extra train.py flags]
    python -m reflow_plugin.ablate -s suite:synthetic -o output/ablation      # balloon ... umbrella

Rows (paper Table 4, ids as in the paper; `--rows` takes the names):

    baseline        4DGS
    fullfm_only     #1  4DGS + full flow matching (no canonical init, no separation)
    wo_align        #2  canonical space without alignment (part 2's `--no-canonical_align`)
    comp_init       #3  complete canonical space only
    sep             #4  + static/dynamic separation
    sep_fullfm      #5  + full flow matching
    ours                + camera flow matching (everything)
    external_flow       "Ours (External Flow)": full flow matching replaced by L1 to DIS flow

Protocol (what every row holds equal): the host's schedule, seed and single-view sampler (one
rendered training view per iteration, the same random sequence of views in every row), the same
densification statistic (the screen-space gradient of the baseline loss of that one view), the
same evaluation. Rows with flow terms (#1, #5, Ours, External Flow) additionally deform and
project ONE partner frame within `--pair_window` of the rendered view (ReFlow's `pair_mode
partner`): it is never rendered and adds nothing to the baseline loss or the densification
statistic. The paper's pairwise batch (both frames rendered, both directions, L_cr) is `--pair_mode
both`; with it the flow rows render two views per iteration and #4 one (not a fair comparison).

Each (scene, row) trains in `OUT/<scene>/<row>` with `train.py` (so every run is an ordinary run,
reproducible from its `config.json`). A run counts as done when `OUT/<scene>/<row>/ablate_done.json`
exists (written after train.py and the flow evaluation succeed); a folder without it is a torn run
and is cleared and redone, so a killed sweep resumes where it stopped. Runs go to submitit: its
LocalExecutor (processes on this machine, at most `--jobs` at a time) or its SlurmExecutor (one
job per run; `--slurm_partition`, `--timeout_min`). Rows that need part 2 (comp_init) say in the
table when the canonical space was unavailable. Outputs: `OUT/ablation.md` (the paper's layout:
one block of PSNR / SSIM / LPIPS per scene and the mean, plus flow EPE and PSNR-dynamic),
`OUT/ablation.json`, `OUT/ablation.csv`. Paths (`-s`, `-o`, and existing files named after `--`) are
taken relative to the folder the command is run from, although the runs start in the checkout.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from baselines.thread_policy import available_cpus

REPO_ROOT = Path(__file__).resolve().parents[1]
SUITES = {"synthetic": ("balloon", "playground", "skating", "truck", "umbrella")}
DONE_FILE = "ablate_done.json"

ROWS: dict[str, tuple[str, list[str]]] = {
    "baseline": ("Baseline (4DGS)", []),
    "fullfm_only": ("#1 FullFM only", ["--plugin", "reflow", "--disable", "comp_init,separation,cam_flow"]),
    "wo_align": ("#2 w/o align", ["--plugin", "reflow", "--disable", "separation,full_flow,cam_flow",
                                  "--no-canonical_align"]),
    "comp_init": ("#3 CompInit", ["--plugin", "reflow", "--disable", "separation,full_flow,cam_flow"]),
    "sep": ("#4 + Sep", ["--plugin", "reflow", "--disable", "full_flow,cam_flow"]),
    "sep_fullfm": ("#5 + FullFM", ["--plugin", "reflow", "--disable", "cam_flow"]),
    "ours": ("Ours", ["--plugin", "reflow"]),
    "external_flow": ("Ours (External Flow)", ["--plugin", "reflow", "--enable", "ext_flow", "--disable", "full_flow"]),
}
PROTOCOL = ("every row: one rendered training view per iteration (the host's seeded sampler), the baseline "
            "loss's densification statistic; rows with flow terms also project (never render) one partner frame")
METRICS = ("PSNR", "SSIM", "LPIPS-vgg", "PSNR-dynamic", "EPE-test")


class AblationError(ValueError):
    """Bad runner input (unknown row or suite, missing scene)."""


@dataclass(frozen=True)
class RunSpec:
    scene: str
    source: Path
    row: str
    run_dir: Path
    command: tuple[str, ...]


def resolve_scenes(source: str) -> list[tuple[str, Path]]:
    """`suite:NAME` -> the suite's scenes under data/synthetic (generated when missing); else one folder."""
    if source.startswith("suite:"):
        name = source.split(":", 1)[1]
        if name not in SUITES:
            raise AblationError(f"unknown suite {name!r}; known: {sorted(SUITES)}")
        return [(scene, REPO_ROOT / "data" / "synthetic" / scene) for scene in SUITES[name]]
    path = Path(source)
    if not path.is_dir():
        raise AblationError(f"scene folder {path} does not exist")
    return [(path.name, path)]


def plan(scenes: list[tuple[str, Path]], rows: list[str], out: Path, extra: list[str],
         table: dict[str, tuple[str, list[str]]] | None = None) -> list[RunSpec]:
    """Every (scene, row) run with its train.py command (rows of `table`, default the ablation's)."""
    table = ROWS if table is None else table
    unknown = [r for r in rows if r not in table]
    if unknown:
        raise AblationError(f"unknown row(s) {unknown}; known: {list(table)}")
    specs = []
    for scene, source in scenes:
        for row in rows:
            run_dir = out / scene / row
            command = (sys.executable, str(REPO_ROOT / "train.py"), "-s", str(source), "-m", str(run_dir), "--quiet",
                       *table[row][1], *extra)
            specs.append(RunSpec(scene, source, row, run_dir, command))
    return specs


def is_done(spec: RunSpec) -> bool:
    return (spec.run_dir / DONE_FILE).is_file()


def execute(spec: RunSpec) -> dict:
    """Train one run (its folder cleared first: a torn run is redone), measure its flow, mark it done."""
    if spec.run_dir.exists():
        shutil.rmtree(spec.run_dir)
    spec.run_dir.mkdir(parents=True)
    if not (spec.source / "poses_bounds.npy").is_file() and spec.source.parent.name == "synthetic":
        subprocess.run([sys.executable, "-m", "baselines.synthetic", "--scene", spec.scene, "--out", str(spec.source),
                        "--quiet"], cwd=REPO_ROOT, check=True)
    start = time.time()
    with open(spec.run_dir / "ablate_train.log", "w") as log:
        result = subprocess.run(list(spec.command), cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT)
    if result.returncode != 0:
        raise RuntimeError(f"{spec.scene}/{spec.row}: train.py exited with {result.returncode} "
                           f"(see {spec.run_dir / 'ablate_train.log'})")
    subprocess.run([sys.executable, "-m", "reflow_plugin.evaluate", "-m", str(spec.run_dir)], cwd=REPO_ROOT,
                   check=True, stdout=subprocess.DEVNULL)
    info = {"scene": spec.scene, "row": spec.row, "command": list(spec.command), "wall_seconds": time.time() - start}
    (spec.run_dir / DONE_FILE).write_text(json.dumps(info, indent=1))
    return info


def make_executor(kind: str, folder: Path, timeout_min: int, partition: str | None):
    """A submitit executor (imported here: only the runner needs it)."""
    import submitit

    if kind == "local":
        executor = submitit.LocalExecutor(folder=str(folder))
        executor.update_parameters(timeout_min=timeout_min)
    elif kind == "slurm":
        executor = submitit.SlurmExecutor(folder=str(folder))
        executor.update_parameters(time=timeout_min, **({"partition": partition} if partition else {}))
    else:
        raise AblationError(f"unknown executor {kind!r}; use local or slurm")
    return executor


def run_all(specs: list[RunSpec], executor, jobs: int, poll_seconds: float = 2.0) -> list[str]:
    """Submit the runs that are not done, at most `jobs` in flight; returns the failures' messages."""
    pending = [s for s in specs if not is_done(s)]
    in_flight: list[tuple[RunSpec, object]] = []
    failures: list[str] = []
    while pending or in_flight:
        while pending and len(in_flight) < max(1, jobs):
            spec = pending.pop(0)
            if is_done(spec):  # finished meanwhile by another runner on the same folder
                continue
            print(f"[ablate] start {spec.scene}/{spec.row}", flush=True)
            in_flight.append((spec, executor.submit(execute, spec)))
        still = []
        for spec, job in in_flight:
            if not job.done():
                still.append((spec, job))
                continue
            try:
                job.result()
                print(f"[ablate] done  {spec.scene}/{spec.row}", flush=True)
            except Exception as exc:  # a failed run is reported, the sweep goes on
                failures.append(f"{spec.scene}/{spec.row}: {exc}")
        if len(still) == len(in_flight) and still:
            time.sleep(poll_seconds)
        in_flight = still
    return failures


def collect(specs: list[RunSpec]) -> dict[str, dict[str, dict]]:
    """{scene: {row: figures}} of the finished runs."""
    table: dict[str, dict[str, dict]] = {}
    for spec in specs:
        if not is_done(spec):
            continue
        results = json.loads((spec.run_dir / "results.json").read_text())
        key = max((k for k in results if k.startswith("ours_")), key=lambda k: int(k.split("_")[1]))
        metrics = results[key]
        flow_path = spec.run_dir / "flow_metrics.json"
        flow = json.loads(flow_path.read_text()).get(key, {}) if flow_path.is_file() else {}
        row = {m: metrics.get(m) for m in ("PSNR", "SSIM", "LPIPS-vgg", "PSNR-dynamic")}
        row["EPE-test"] = flow["test"]["epe"] if flow.get("available") else None
        row["LPIPS_unavailable"] = metrics.get("LPIPS_unavailable")
        row["comp_init"] = results.get("reflow", {}).get("comp_init")
        # which initial cloud the run trained from (the check may have replaced the row's own)
        row["initial_cloud"] = results.get("reflow", {}).get("canonical_check", {}).get("used")
        table.setdefault(spec.scene, {})[spec.row] = row
    return table


def _cell(value, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown(table: dict[str, dict[str, dict]], rows: list[str]) -> str:
    """The paper's layout: one row per ablation row; per scene PSNR / SSIM / LPIPS, then the mean."""
    scenes = list(table)
    header = ["Method", *[f"{s} PSNR / SSIM / LPIPS" for s in scenes], "Mean PSNR / SSIM / LPIPS",
              "Mean PSNR-dynamic", "Mean EPE-test"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    notes = set()
    for row in rows:
        cells, values = [ROWS[row][0]], []
        for scene in scenes:
            figures = table[scene].get(row)
            if figures is None:
                cells.append("not run")
                continue
            values.append(figures)
            cells.append(" / ".join((_cell(figures["PSNR"], 2), _cell(figures["SSIM"], 3), _cell(figures["LPIPS-vgg"], 3))))
            if figures.get("LPIPS_unavailable"):
                notes.add("LPIPS: " + figures["LPIPS_unavailable"])
            if figures.get("comp_init") and row in ("wo_align", "comp_init", "sep", "sep_fullfm", "ours", "external_flow"):
                notes.add(f"{ROWS[row][0]}: comp_init {figures['comp_init']}")
            used = figures.get("initial_cloud")
            if used and not used.startswith("canonical space"):
                # e.g. "#2 w/o align" whose raw cloud failed the check: it trained from a fallback
                notes.add(f"{ROWS[row][0]} on {scene}: the initial-cloud check replaced the row's cloud ({used})")

        def mean(metric: str):
            got = [v[metric] for v in values if v.get(metric) is not None]
            return float(np.mean(got)) if got and len(got) == len(values) else None

        cells.append(" / ".join((_cell(mean("PSNR"), 2), _cell(mean("SSIM"), 3), _cell(mean("LPIPS-vgg"), 3))))
        cells += [_cell(mean("PSNR-dynamic"), 2), _cell(mean("EPE-test"), 3)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines + [""] + [f"- {n}" for n in [f"Protocol: {PROTOCOL}", *sorted(notes)]])


def write_outputs(table: dict[str, dict[str, dict]], rows: list[str], out: Path) -> str:
    text = markdown(table, rows)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ablation.md").write_text(text + "\n")
    (out / "ablation.json").write_text(json.dumps(table, indent=1))
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["scene", "row", *METRICS])
    for scene, by_row in table.items():
        for row, figures in by_row.items():
            writer.writerow([scene, row, *[figures.get(m) for m in METRICS]])
    (out / "ablation.csv").write_text(buffer.getvalue())
    return text


def parse_runner_args(argv: list[str] | None, prog: str, description: str, names_flag: str,
                      table: dict[str, tuple[str, list[str]]]) -> tuple[argparse.Namespace, list[str], list[str]]:
    """The command line shared by the ablation runner and the sweep: (args, chosen names, train.py extras).

    Everything after ``--`` goes to every train.py run; ``--<names_flag>`` picks entries of ``table``.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        extra, argv = argv[argv.index("--") + 1:], argv[:argv.index("--")]
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("-s", "--source", required=True, help="a scene folder or suite:synthetic")
    parser.add_argument("-o", "--out", type=Path, required=True)
    parser.add_argument(f"--{names_flag}", default=",".join(table), help=f"comma-separated, of {list(table)}")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--executor", default="local", choices=("local", "slurm"))
    parser.add_argument("--timeout_min", type=int, default=240)
    parser.add_argument("--slurm_partition")
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        example = " ".join(unknown[:2])
        parser.error(f"unrecognized arguments: {' '.join(unknown)} (train.py flags go after '--', "
                     f"e.g. {prog} -s ... -o ... -- {example})")
    names = [n.strip() for n in getattr(args, names_flag).split(",") if n.strip()]
    if not names:
        parser.error(f"--{names_flag} names none of {list(table)}")
    if "--no-eval" in extra:  # the tables are of held-out views (results.json): a run without them fails late
        parser.error("--no-eval after '--': the table reports held-out views; drop it")
    if not str(args.out).strip() or not args.source.strip():
        parser.error("-s and -o must not be empty (an unset shell variable?)")
    # runs start from the checkout (cwd=REPO_ROOT): paths typed relative to the caller's folder go absolute
    args.out = Path(os.path.abspath(args.out))
    if not args.source.startswith("suite:"):
        args.source = os.path.abspath(args.source)
    extra = [os.path.abspath(a) if not a.startswith("-") and os.path.exists(a) else a for a in extra]
    return args, names, extra


def share_threads(environ: MutableMapping[str, str], jobs: int, executor: str) -> str | None:
    """OMP_NUM_THREADS for local runs in parallel: the available CPUs split between the jobs.

    Runs started together each see an idle machine and would take every CPU (train.py's thread
    policy looks at the load only at start); oversubscribed OpenMP threads then wait for each
    other at every parallel op. Left alone when set by the user, for one job, or on Slurm.
    """
    if executor != "local" or jobs <= 1 or "OMP_NUM_THREADS" in environ:
        return None
    environ["OMP_NUM_THREADS"] = str(max(1, available_cpus() // jobs))
    return environ["OMP_NUM_THREADS"]


def start_runs(args: argparse.Namespace, names: list[str], extra: list[str], label: str,
               table: dict[str, tuple[str, list[str]]] | None = None) -> tuple[list[RunSpec], list[str]] | None:
    """Plan and run what is not done yet; (specs, failures), or None after printing a bad-input error."""
    try:
        specs = plan(resolve_scenes(args.source), names, args.out, extra, table=table)
        executor = make_executor(args.executor, args.out / "_submitit", args.timeout_min, args.slurm_partition)
    except AblationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    done = sum(is_done(s) for s in specs)
    if done:
        print(f"[{label}] {done} of {len(specs)} runs already done (kept)")
    threads = share_threads(os.environ, args.jobs, args.executor)
    if threads is not None:
        print(f"[{label}] {args.jobs} local jobs: OMP_NUM_THREADS={threads} each (set it to choose)")
    return specs, run_all(specs, executor, args.jobs)


def main(argv: list[str] | None = None) -> int:
    args, rows, extra = parse_runner_args(argv, "python -m reflow_plugin.ablate", __doc__.splitlines()[0], "rows", ROWS)
    started = start_runs(args, rows, extra, "ablate")
    if started is None:
        return 2
    specs, failures = started
    print(write_outputs(collect(specs), rows, args.out))
    for failure in failures:
        print(f"error: {failure}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
