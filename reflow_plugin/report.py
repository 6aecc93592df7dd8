"""What accuracy costs in time: PSNR-versus-training-time curves and the paper-style cost table.

    python -m reflow_plugin.report OUT [--plot OUT/accuracy_vs_time.png] [--pareto]

OUT is an ablation folder (`OUT/<scene>/<row>/`, from `python -m reflow_plugin.ablate`) or any
folder of runs. Per run it reads `train_log.jsonl` (every "test" event carries the held-out PSNR
and the wall / CPU seconds spent in training steps so far, evaluation and saving excluded; the
"train_end" event the totals and the peak RSS), `results.json` (final metrics, render ms per view)
and the size of the final `point_cloud/iteration_N` folder. Writes the plot (one panel per scene,
one curve per row) and `OUT/cost.md`, the cost table averaged over scenes: training time (wall and
CPU), peak memory, render FPS, model size on disk, final PSNR. Runs from older code without
timing fields in their "test" events are listed as missing, not guessed.

`--pareto` (for a sweep, `python -m reflow_plugin.sweep`) also marks each scene's Pareto front of
the runs' final (training wall time, test PSNR) points in the plot and writes `OUT/pareto.md`:
per scene every run's time and PSNR, the runs on the front starred.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from baselines.fourdgs.run_log import read_log

COST_COLUMNS = ("train_s", "train_cpu_s", "peak_rss_mib", "render_fps", "model_mib", "PSNR")


def find_runs(out: Path) -> dict[tuple[str, str], Path]:
    """{(scene, row): run folder} for every folder under OUT holding a finished run."""
    runs = {}
    for log in sorted(out.glob("**/train_log.jsonl")):
        run = log.parent
        if not (run / "results.json").is_file():
            continue
        rel = run.relative_to(out).parts
        scene, row = (rel[0], rel[-1]) if len(rel) >= 2 else ("-", rel[0] if rel else run.name)
        runs[(scene, row)] = run
    return runs


def curve(run: Path) -> list[tuple[float, float, float]]:
    """[(train wall s, train CPU s, test PSNR)] of the run's "test" events that carry timing."""
    points = []
    for record in read_log(run / "train_log.jsonl"):
        if record.get("kind") == "test" and "train_seconds" in record and record.get("test_psnr") is not None:
            points.append((record["train_seconds"], record["train_cpu_seconds"], record["test_psnr"]))
    return points


def cost(run: Path) -> dict[str, float | None]:
    """The cost-table figures of one run (None where the run does not have them)."""
    end = [r for r in read_log(run / "train_log.jsonl") if r.get("kind") == "train_end"]
    try:
        results = json.loads((run / "results.json").read_text())
    except ValueError as err:
        raise ValueError(f"{run / 'results.json'}: not JSON ({err})") from None
    keys = [k for k in results if k.startswith("ours_")]
    final = results[max(keys, key=lambda k: int(k.split("_")[1]))] if keys else {}
    clouds = sorted((run / "point_cloud").glob("iteration_*"), key=lambda p: int(p.name.split("_")[1]))
    size = sum(f.stat().st_size for f in clouds[-1].iterdir() if f.is_file()) / 2**20 if clouds else None
    last = end[-1] if end else {}
    ms = final.get("render_ms_per_view")
    return {"train_s": last.get("train_seconds"), "train_cpu_s": last.get("train_cpu_seconds"),
            "peak_rss_mib": last.get("peak_rss_mib"), "render_fps": 1000.0 / ms if ms else None,
            "model_mib": size, "PSNR": final.get("PSNR")}


def cost_table(runs: dict[tuple[str, str], Path]) -> str:
    """Markdown: one line per row, each figure averaged over the scenes that have it."""
    by_row: dict[str, list[dict]] = {}
    for (_, row), run in runs.items():
        by_row.setdefault(row, []).append(cost(run))
    fmt = {"train_s": "{:.0f}", "train_cpu_s": "{:.0f}", "peak_rss_mib": "{:.0f}", "render_fps": "{:.1f}",
           "model_mib": "{:.2f}", "PSNR": "{:.2f}"}
    lines = ["| row | scenes | training s (wall) | training s (CPU) | peak RSS MiB | render FPS | model MiB | PSNR |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row, figures in by_row.items():
        cells = []
        for column in COST_COLUMNS:
            values = [f[column] for f in figures if f[column] is not None]
            cells.append(fmt[column].format(float(np.mean(values))) if values else "-")
        lines.append(f"| {row} | {len(figures)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def pareto_front(points: dict[str, tuple[float, float]]) -> list[str]:
    """Names whose (time, PSNR) no other point beats: at most the time and at least the PSNR, one strictly.

    Returned by increasing time."""
    front = []
    for name, (t, q) in points.items():
        dominated = any(t2 <= t and q2 >= q and (t2 < t or q2 > q) for other, (t2, q2) in points.items()
                        if other != name)
        if not dominated:
            front.append(name)
    return sorted(front, key=lambda n: points[n][0])


def final_points(runs: dict[tuple[str, str], Path]) -> dict[str, dict[str, tuple[float, float]]]:
    """{scene: {row: (training wall s, final test PSNR)}} of the runs whose totals were recorded."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for (scene, row), run in runs.items():
        figures = cost(run)
        if figures["train_s"] is not None and figures["PSNR"] is not None:
            out.setdefault(scene, {})[row] = (float(figures["train_s"]), float(figures["PSNR"]))
    return out


def pareto_table(points: dict[str, dict[str, tuple[float, float]]]) -> str:
    """Markdown: per scene, each run's time and PSNR by increasing time, the front starred."""
    lines = ["| scene | run | training s (wall) | test PSNR | on the front |", "|---|---|---:|---:|:---:|"]
    for scene, by_row in sorted(points.items()):
        front = set(pareto_front(by_row))
        for row, (t, q) in sorted(by_row.items(), key=lambda item: item[1][0]):
            lines.append(f"| {scene} | {row} | {t:.0f} | {q:.2f} | {'*' if row in front else ''} |")
    return "\n".join(lines)


def plot(runs: dict[tuple[str, str], Path], path: Path, pareto: bool = False) -> list[str]:
    """PSNR against training wall time, one panel per scene; returns the runs without timing.

    With ``pareto`` each scene's front of final points is drawn as a step line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({scene for scene, _ in runs})
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.4), squeeze=False)
    missing = []
    for ax, scene in zip(axes[0], scenes):
        for (s, row), run in sorted(runs.items()):
            if s != scene:
                continue
            points = curve(run)
            if not points:
                missing.append(f"{scene}/{row}")
                continue
            ax.plot([p[0] for p in points], [p[2] for p in points], marker="o", label=row)
        if pareto:
            finals = final_points({k: v for k, v in runs.items() if k[0] == scene}).get(scene, {})
            front = pareto_front(finals)
            if front:
                ax.step([finals[n][0] for n in front], [finals[n][1] for n in front], where="post", color="black",
                        linewidth=2, alpha=0.5, label="Pareto front")
        ax.set_title(scene)
        ax.set_xlabel("training time (s, wall)")
        ax.set_ylabel("test PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return missing


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except (OSError, ValueError) as err:  # an unreadable log or results.json: one line naming it
        text = str(err).strip()
        print(f"error: {text.splitlines()[0] if text else type(err).__name__}", file=sys.stderr)
        return 2


def _main(argv: list[str] | None) -> int:
    parser = argparse.ArgumentParser(prog="python -m reflow_plugin.report", description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--pareto", action="store_true", help="mark the Pareto front; write OUT/pareto.md")
    args = parser.parse_args(argv)
    runs = find_runs(args.out)
    if not runs:
        print(f"error: no finished run (train_log.jsonl + results.json) under {args.out}", file=sys.stderr)
        return 2
    missing = plot(runs, args.plot or args.out / "accuracy_vs_time.png", pareto=args.pareto)
    table = cost_table(runs)
    (args.out / "cost.md").write_text(table + "\n")
    print(table)
    if args.pareto:
        front = pareto_table(final_points(runs))
        (args.out / "pareto.md").write_text(front + "\n")
        print("\n" + front)
    for name in missing:
        print(f"warning: {name} has no timed test events (trained before they were recorded)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
