"""Convergence study: held-out PSNR and Gaussian count against the fine-iteration budget, both methods.

    python benchmarks/convergence.py [--captures nvidia_balloon1,panoptic_basketball]
                                     [--methods baseline,reflow] [--budgets 1000,3000,7000,14000]
                                     [--coarse_iterations 3000] [--downscale K]
                                     [--resolution nvidia_balloon1=8,...]
                                     [--data data/real] [--out output/convergence] [--seed 0]
                                     [--plot PNG] [--report-only]
                                     [--jobs 1] [--chunk-seconds S] [--images DIR]
                                     [-- extra train.py flags]

Each (capture, method, budget) is an ordinary `train.py` run made by `real_suite.run_one` (same
run folders, `real_done.json` done-markers holding the exact command and the code version, same
masked metrics with the dataset's true masks) in `OUT/<capture>/<method>/fine_<budget>`. A killed
study reruns only the runs without a done-marker; `--report-only` trains nothing and tabulates
what is done. Runs go longest budget first (the most informative figures land first when time
runs out), `--jobs` at a time (one thread each when more than one: on a GPU, where a step at these
sizes is bound by kernel launches, several trainings share the device well). `--images DIR`
writes the side-by-side held-out images (ground truth | baseline | ReFlow) of each capture's
longest budget that every method finished, as real_suite.py does.

The schedule rule. The family configs (NVIDIA, panoptic and prepared clips: 4DGS's
arguments/hypernerf/default.py over OptimizationParams' defaults) are written for 14,000 fine
iterations. A run of B fine iterations multiplies every iteration-valued field of the
densification and learning-rate schedule by s = B / 14000 (rounded, at least `MIN_SCALED`):
`densify_from_iter`, `densify_until_iter`, `pruning_from_iter`, `densification_interval`,
`pruning_interval`, `opacity_reset_interval` (300,000 in the config, i.e. never; stays never)
and `position_lr_max_steps` (the position, deformation and grid rates' decay horizon). So a
budget trains the same schedule compressed: it densifies over the same fraction of the run, the
same number of times (until the interval floor of 10 iterations binds, B < 1400: gradient
statistics accumulated over fewer views are too noisy), and ends at the same learning rates.
Not scaled: `coarse_iterations` (a flag, the same for every budget, so the curve is about the fine
stage; note the coarse stage reads the same densification fields, with its own iteration count),
`stall_iterations` (a failure guard), `batch_size`, the thresholds. ReFlow's own schedule is in
fractions of the fine stage (`dynamic_settle_fraction`, `curriculum_fraction`) and scales by
itself. The exact flags of each run are in its `real_done.json` and in the JSON written here.

Resolution: each capture's registry resolution (`train.py -r`, the real-capture benchmark's), times
`--downscale K` (default 1), except where `--resolution NAME=R` names it. `--downscale 2` trains
every capture at half the benchmark's image size: about 160 pixels across (Balloon1 120x68,
basketball 160x90, the prepared DAVIS clips 160x90), the study's CPU size.

Writes `OUT/convergence.json` (schedule, flags and figures per run), `OUT/convergence.md` (one
table: PSNR all / inside the true masks / outside, SSIM, Gaussians at the end, wall seconds, CPU seconds of the training steps) and a
PNG (`--plot`, default `OUT/convergence.png`): PSNR (solid, left axis) and Gaussians (dashed, right axis, log) against fine
iterations, one panel per capture, both methods.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.cli import split_passthrough  # noqa: E402
from benchmarks import real_suite  # noqa: E402
from benchmarks.real_captures import DEFAULT_DATA, Capture, CaptureError, require_ready, select  # noqa: E402

FULL_BUDGET = 14_000  # fine iterations of the family configs (arguments/hypernerf/default.py)
# The family configs' values of every iteration-valued schedule field (tests/test_convergence.py
# checks them against arguments/params.py and the configs).
FULL_SCHEDULE = {
    "densify_from_iter": 500,
    "densify_until_iter": 10_000,
    "pruning_from_iter": 500,
    "densification_interval": 100,
    "pruning_interval": 100,
    "opacity_reset_interval": 300_000,
    "position_lr_max_steps": 20_000,
}
MIN_SCALED = {"densification_interval": 10, "pruning_interval": 10}  # others: at least 1
DEFAULT_BUDGETS = (1000, 3000, 7000, 14_000)
DEFAULT_CAPTURES = ("nvidia_balloon1", "panoptic_basketball")
COLUMNS = ("PSNR", "PSNR-mask", "PSNR-outside", "SSIM", "Gaussians", "train_s", "train_cpu_s", "MLP")


def scaled_schedule(budget: int) -> dict[str, int]:
    """The iteration-valued fields for a run of `budget` fine iterations (see the module docstring)."""
    if budget < 1:
        raise ValueError(f"a budget must be >= 1 fine iteration, got {budget}")
    return {name: max(MIN_SCALED.get(name, 1), round(value * budget / FULL_BUDGET))
            for name, value in FULL_SCHEDULE.items()}


def schedule_flags(budget: int) -> list[str]:
    """train.py flags of the scaled schedule."""
    return [item for name, value in scaled_schedule(budget).items() for item in (f"--{name}", str(value))]


DOWNSCALE_FACTORS = (1, 2, 4, 8)  # train.py -r values that divide the image size (baselines/data/resolution.py)


def with_resolutions(captures: list[Capture], downscale: int, named: str | None) -> list[Capture]:
    """The captures with train.py's -r set: the registry's times `downscale`, or what `named`
    (`--resolution NAME=R,...`) gives for a capture.

    Raises:
        CaptureError: a factor below 1, a product that is not one of train.py's downscale factors
            (1, 2, 4, 8: any other -r is a width in pixels, so -r 4 x 3 = 12 would train 12 px wide
            images) for a capture `named` does not set, or a malformed `named`.
    """
    if downscale < 1:
        raise CaptureError(f"--downscale {downscale}: want a factor >= 1")
    scaled = [dataclasses.replace(c, resolution=c.resolution * downscale) for c in captures]
    resolutions = real_suite.parse_resolutions(named, scaled)
    set_by_name = {item.partition("=")[0] for item in (named or "").split(",") if item}
    for capture in captures:
        product = capture.resolution * downscale
        if downscale > 1 and capture.name not in set_by_name and product not in DOWNSCALE_FACTORS:
            raise CaptureError(f"--downscale {downscale}: {capture.name}'s -r {capture.resolution} x {downscale} = "
                               f"{product} is no downscale factor of train.py (1, 2, 4, 8; other values are a "
                               f"width in pixels); choose another K or set it with --resolution {capture.name}=R")
    return [dataclasses.replace(c, resolution=resolutions[c.name]) for c in scaled]


def run_folder(out: Path, capture: str, method: str, budget: int) -> Path:
    return out / capture / method / f"fine_{budget}"


def final_gaussians(run: Path) -> int | None:
    """Gaussian count at the last logged iteration of the fine stage (train_log.jsonl)."""
    last = None
    for line in (run / "train_log.jsonl").read_text().splitlines():
        if line.strip():
            record = json.loads(line)
            if record.get("kind") == "iter" and record.get("stage") == "fine" and "num_gaussians" in record:
                last = record["num_gaussians"]
    return last


def table(rows: list[dict]) -> str:
    """Markdown: one line per (capture, method, budget), in that order."""
    fmt = {"SSIM": "{:.3f}", "Gaussians": "{:,}", "train_s": "{:.0f}", "train_cpu_s": "{:.0f}", "MLP": "{}"}
    lines = ["| capture | method | fine its | " + " | ".join(COLUMNS) + " |", "|---|---|---:|" + "---:|" * len(COLUMNS)]
    for row in sorted(rows, key=lambda r: (r["capture"], r["method"], r["budget"])):
        if "failed" in row:
            lines.append(f"| {row['capture']} | {row['method']} | {row['budget']} | FAILED: "
                         f"{row['failed'].replace('|', '/')} |" + " |" * (len(COLUMNS) - 1))
            continue
        cells = " | ".join("-" if row.get(c) is None else fmt.get(c, "{:.2f}").format(row[c]) for c in COLUMNS)
        lines.append(f"| {row['capture']} | {row['method']} | {row['budget']} | {cells} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, title: str = "") -> Path | None:
    """PSNR (solid) and Gaussians (dashed, log) against fine iterations; one panel per capture."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [r for r in rows if "failed" not in r and r.get("PSNR") is not None]
    captures = sorted({r["capture"] for r in done})
    if not captures:
        return None
    colours = {"baseline": "tab:blue", "reflow": "tab:red"}
    fig, axes = plt.subplots(1, len(captures), figsize=(5.2 * len(captures), 4.0), squeeze=False)
    for ax, capture in zip(axes[0], captures):
        counts = ax.twinx()
        for method in sorted({r["method"] for r in done if r["capture"] == capture}):
            mine = sorted((r for r in done if r["capture"] == capture and r["method"] == method), key=lambda r: r["budget"])
            colour = colours.get(method, "tab:green")
            budgets = [r["budget"] for r in mine]
            ax.plot(budgets, [r["PSNR"] for r in mine], "o-", color=colour, label=f"{method} PSNR")
            masked = [(r["budget"], r["PSNR-mask"]) for r in mine if r.get("PSNR-mask") is not None]
            if masked:
                ax.plot(*zip(*masked), "^:", color=colour, alpha=0.7, label=f"{method} PSNR in mask")
            gaussians = [(r["budget"], r["Gaussians"]) for r in mine if r.get("Gaussians")]
            if gaussians:
                counts.plot(*zip(*gaussians), "s--", color=colour, alpha=0.5, label=f"{method} Gaussians")
        ax.set_xscale("log")
        counts.set_yscale("log")
        ax.set_title(capture)
        ax.set_xlabel("fine iterations")
        ax.set_ylabel("held-out PSNR (dB)")
        counts.set_ylabel("Gaussians at the end")
        handles = ax.get_legend_handles_labels()
        more = counts.get_legend_handles_labels()
        ax.legend(handles[0] + more[0], handles[1] + more[1], fontsize=7, loc="lower right")
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", default=",".join(DEFAULT_CAPTURES), help="comma list of registry names")
    parser.add_argument("--methods", default=",".join(real_suite.DEFAULT_METHODS))
    parser.add_argument("--budgets", default=",".join(map(str, DEFAULT_BUDGETS)), help="comma list of fine iterations")
    parser.add_argument("--coarse_iterations", type=int, default=3000, help="the same for every budget")
    parser.add_argument("--downscale", type=int, default=1, metavar="K",
                        help="train.py -r = the registry's resolution times K (default 1; the product must be "
                             "a downscale factor: 1, 2, 4 or 8)")
    parser.add_argument("--resolution", help="NAME=R,... train.py -r per capture (wins over --downscale)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=ROOT / "output" / "convergence")
    parser.add_argument("--plot", type=Path, default=None,
                        help="PNG to write (default OUT/convergence.png; the documented plot is docs/images/convergence.png)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--report-only", action="store_true", help="train nothing; tabulate the finished runs")
    parser.add_argument("--chunk-seconds", type=float, metavar="S",
                        help="train at most about S seconds in this call, then checkpoint and exit 3; the next "
                             "call continues (real_suite.py --chunk-seconds)")
    parser.add_argument("--jobs", type=int, default=1, help="trainings at once (one thread each when > 1)")
    parser.add_argument("--images", type=Path, help="write real_<capture>.jpg side-by-side images here")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, extra = split_passthrough(argv)
    args = build_parser().parse_args(argv)
    try:
        if args.jobs < 1:
            raise CaptureError(f"--jobs {args.jobs}: want 1 or more trainings at once")
        real_suite.check_chunk_seconds(args.chunk_seconds)
        captures = select(args.captures)
        methods = real_suite.parse_methods(args.methods)
        try:
            budgets = sorted({int(b) for b in args.budgets.split(",") if b})
        except ValueError:
            raise CaptureError(f"--budgets {args.budgets!r}: want a comma list of whole numbers") from None
        if not budgets or budgets[0] < 1:
            raise CaptureError(f"--budgets {args.budgets!r}: want fine iterations >= 1")
        captures = with_resolutions(captures, args.downscale, args.resolution)
        require_ready(captures, args.data)
    except CaptureError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    threads = 1 if args.jobs > 1 else int(os.environ.get("OMP_NUM_THREADS", "0")) or max(1, os.cpu_count() or 1)
    jobs = sorted(((c, m, b) for c in captures for m in methods for b in budgets), key=lambda j: -j[2])
    outcome: dict[tuple[str, str, int], Path | str] = {}

    def train(job: tuple[Capture, str, int], chunk_seconds: float | None = None) -> Path:
        capture, method, budget = job
        schedule = {"coarse_iterations": args.coarse_iterations, "iterations": budget, "seed": args.seed}
        return real_suite.run_one(capture, method, args.data, args.out, schedule, [*schedule_flags(budget), *extra],
                                  threads, run=run_folder(args.out, capture.name, method, budget),
                                  chunk_seconds=chunk_seconds)

    try:
        if args.report_only:
            outcome = {(c.name, m, b): run_folder(args.out, c.name, m, b) for c, m, b in jobs
                       if (run_folder(args.out, c.name, m, b) / real_suite.DONE_FILE).is_file()}
        elif args.chunk_seconds is not None:
            runs = real_suite.run_chunked(jobs, args.chunk_seconds, train, workers=args.jobs)
            outcome = {(c.name, m, b): r for (c, m, b), r in zip(jobs, runs)}
        else:
            def attempt(job: tuple[Capture, str, int]) -> Path | str:
                """The run folder, or the failure's one-line reason (the other runs go on)."""
                try:
                    return train(job)
                except real_suite.TrainingFailed as failure:
                    print(f"error: {job[0].name}/{job[1]}/{job[2]}: {failure}", file=sys.stderr)
                    return str(failure)
                finally:
                    print(f"done: {job[0].name}/{job[1]}/{job[2]}", flush=True)

            with ThreadPoolExecutor(max_workers=args.jobs) as pool:
                runs = list(pool.map(attempt, jobs))
            outcome = {(c.name, m, b): r for (c, m, b), r in zip(jobs, runs)}
    except real_suite.ChunkPending as pending:
        print(f"pending: {pending}", file=sys.stderr)
        return 3
    except real_suite.SuiteError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    rows = []
    for capture in captures:
        mine = {k: v for k, v in outcome.items() if k[0] == capture.name}
        if not mine:
            continue
        scene = real_suite.load_capture(capture, args.data)
        masks = real_suite.eval_masks(capture, scene, args.out)
        for (name, method, budget), result in mine.items():
            row = {"capture": name, "method": method, "budget": budget, "resolution": capture.resolution,
                   "coarse_iterations": args.coarse_iterations, "flags": schedule_flags(budget) + extra}
            if isinstance(result, str):
                rows.append({**row, "failed": result})
                continue
            figures = real_suite.summarise(result, masks, scene)
            row.update({k: figures.get(k) for k in ("PSNR", "SSIM", "PSNR-mask", "PSNR-outside", "mask %", "code", "MLP")})
            row["Gaussians"] = final_gaussians(result)
            row["train_s"], row["train_cpu_s"] = figures.get("train_s"), figures.get("train_cpu_s")
            row["command"] = json.loads((result / real_suite.DONE_FILE).read_text())["command"]
            rows.append(row)
        if args.images is not None:
            finished = [b for b in budgets if all(isinstance(mine.get((capture.name, m, b)), Path) for m in methods)]
            if finished:
                real_suite.side_by_side(capture, {m: mine[capture.name, m, finished[-1]] for m in methods},
                                        masks, args.images)
    text = table(rows)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "convergence.md").write_text(text + "\n")
    (args.out / "convergence.json").write_text(json.dumps(
        {"full_budget": FULL_BUDGET, "full_schedule": FULL_SCHEDULE, "budgets": budgets,
         "coarse_iterations": args.coarse_iterations, "rows": rows}, indent=1, default=str))
    resolution_note = ", ".join(f"{c.name} -r {c.resolution}" for c in captures)
    plot(rows, args.plot or args.out / "convergence.png", f"coarse {args.coarse_iterations} its; {resolution_note}; densification scaled to the budget")
    return 1 if any(isinstance(r, str) for r in outcome.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
