"""The ablation runner: planning, resume after a kill, the table, and submitit's local executor end to end."""
from __future__ import annotations

import json
import types
from pathlib import Path

import pytest

from reflow_plugin import ablate
from tests.test_trainer import FAST


def _fake_done_run(spec: ablate.RunSpec, psnr: float, epe: float | None = 0.5, used: str | None = None) -> None:
    spec.run_dir.mkdir(parents=True, exist_ok=True)
    results = {"ours_100": {"PSNR": psnr - 1, "SSIM": 0.5}, "ours_200": {
        "PSNR": psnr, "SSIM": 0.9, "LPIPS-vgg": None, "PSNR-dynamic": psnr - 5,
        "LPIPS_unavailable": "no lpips package"}}
    if used is not None:
        results["reflow"] = {"canonical_check": {"used": used}}
    (spec.run_dir / "results.json").write_text(json.dumps(results))
    flow = {"ours_200": {"available": epe is not None, "test": {"epe": epe}}}
    (spec.run_dir / "flow_metrics.json").write_text(json.dumps(flow))
    (spec.run_dir / ablate.DONE_FILE).write_text("{}")


def test_plan_rejects_unknown_rows_and_suites(tmp_path):
    with pytest.raises(ablate.AblationError, match="unknown row"):
        ablate.plan([("s", tmp_path)], ["baseline", "nope"], tmp_path / "out", [])
    with pytest.raises(ablate.AblationError, match="unknown suite"):
        ablate.resolve_scenes("suite:nope")
    with pytest.raises(ablate.AblationError, match="does not exist"):
        ablate.resolve_scenes(str(tmp_path / "missing"))
    specs = ablate.plan([("s", tmp_path)], ["baseline", "ours"], tmp_path / "out", ["--iterations", "5"])
    assert "--plugin" not in specs[0].command and specs[1].command[-2:] == ("--iterations", "5")
    assert specs[1].run_dir == tmp_path / "out" / "s" / "ours"


class _RecordingExecutor:
    """Runs nothing: records what would be submitted and marks it done."""

    def __init__(self) -> None:
        self.submitted: list[str] = []

    def submit(self, fn, spec):
        self.submitted.append(spec.row)
        _fake_done_run(spec, 20.0)
        return types.SimpleNamespace(done=lambda: True, result=lambda: None)


def test_a_killed_sweep_resumes_and_redoes_only_torn_runs(tmp_path):
    specs = ablate.plan([("s", tmp_path)], ["baseline", "sep", "ours"], tmp_path / "out", [])
    _fake_done_run(specs[0], 25.0)  # finished before the kill
    specs[1].run_dir.mkdir(parents=True)  # torn: killed mid-training, no done marker
    (specs[1].run_dir / "results.json").write_text("{}")
    executor = _RecordingExecutor()
    assert ablate.run_all(specs, executor, jobs=2) == []
    assert executor.submitted == ["sep", "ours"]
    again = _RecordingExecutor()
    ablate.run_all(specs, again, jobs=2)
    assert again.submitted == []  # nothing redone


def test_execute_clears_a_torn_folder(tmp_path, monkeypatch):
    spec = ablate.plan([("s", tmp_path)], ["baseline"], tmp_path / "out", [])[0]
    spec.run_dir.mkdir(parents=True)
    (spec.run_dir / "stale.txt").write_text("from the killed run")
    calls = []
    monkeypatch.setattr(ablate.subprocess, "run", lambda cmd, **kw: calls.append(cmd) or types.SimpleNamespace(returncode=0))
    ablate.execute(spec)
    assert not (spec.run_dir / "stale.txt").exists() and ablate.is_done(spec) and len(calls) == 2


def test_table_layout_means_and_notes(tmp_path):
    scenes = [("a", tmp_path), ("b", tmp_path)]
    specs = ablate.plan(scenes, ["baseline", "ours"], tmp_path / "out", [])
    used = (None, "canonical space", None, "per-frame fits to the sparse points")  # b/ours: the check's fallback
    for spec, psnr, cloud in zip(specs, (20.0, 22.0, 24.0, 26.0), used):  # a/baseline, a/ours, b/baseline, b/ours
        _fake_done_run(spec, psnr, used=cloud)
    text = ablate.write_outputs(ablate.collect(specs), ["baseline", "ours"], tmp_path / "out")
    lines = text.splitlines()
    assert lines[0].startswith("| Method | a PSNR / SSIM / LPIPS | b PSNR / SSIM / LPIPS | Mean")
    assert lines[2] == "| Baseline (4DGS) | 20.00 / 0.900 / - | 24.00 / 0.900 / - | 22.00 / 0.900 / - | 17.00 | 0.500 |"
    assert lines[3].startswith("| Ours | 22.00 / 0.900 / - | 26.00 / 0.900 / - | 24.00")
    assert "- LPIPS: no lpips package" in lines
    notes = [line for line in lines if "initial-cloud check" in line]
    assert notes == ["- Ours on b: the initial-cloud check replaced the row's cloud (per-frame fits to the sparse points)"]
    csv_rows = (tmp_path / "out" / "ablation.csv").read_text().splitlines()
    assert csv_rows[0] == "scene,row,PSNR,SSIM,LPIPS-vgg,PSNR-dynamic,EPE-test" and len(csv_rows) == 5
    assert json.loads((tmp_path / "out" / "ablation.json").read_text())["b"]["ours"]["PSNR"] == 26.0


def test_local_executor_end_to_end_two_rows(tiny_scene, tmp_path):
    out = tmp_path / "ablation"
    extra = ["--configs", str(Path(ablate.REPO_ROOT) / "arguments/synthetic/default.py"), "--coarse_iterations", "2",
             "--iterations", "6", *FAST, "--flow_vis_every", "0"]
    # --flow_vis_every is a ReFlow flag: the baseline row would reject it, so run two ReFlow rows
    code = ablate.main(["-s", str(tiny_scene), "-o", str(out), "--rows", "ours,external_flow", "--jobs", "2", "--", *extra])
    assert code == 0
    table = json.loads((out / "ablation.json").read_text())[tiny_scene.name]
    assert set(table) == {"ours", "external_flow"} and all(r["PSNR"] > 5 for r in table.values())
    assert (out / tiny_scene.name / "ours" / ablate.DONE_FILE).is_file()
    assert "| Ours (External Flow) |" in (out / "ablation.md").read_text()
    from reflow_plugin import report  # the runs' own logs carry the timing the report needs

    assert report.main([str(out)]) == 0
    cost_lines = (out / "cost.md").read_text().splitlines()
    assert any(line.startswith("| ours | 1 |") and "| - |" not in line for line in cost_lines), cost_lines


def _fake_logged_run(run: Path, points: list[tuple[float, float]], rss: float, ms: float, timed: bool = True) -> None:
    run.mkdir(parents=True)
    events = [{"kind": "test", "iteration": i, "test_psnr": p, **({"train_seconds": t, "train_cpu_seconds": 2 * t}
                                                                    if timed else {})}
              for i, (t, p) in enumerate(points, 1)]
    events.append({"kind": "train_end", "train_seconds": points[-1][0], "train_cpu_seconds": 2 * points[-1][0],
                   "peak_rss_mib": rss})
    (run / "train_log.jsonl").write_text("\n".join(json.dumps(e) for e in events))
    (run / "results.json").write_text(json.dumps({"ours_9": {"PSNR": points[-1][1], "render_ms_per_view": ms}}))
    cloud = run / "point_cloud" / "iteration_9"
    cloud.mkdir(parents=True)
    (cloud / "point_cloud.ply").write_bytes(b"x" * 2**20)


def test_report_cost_table_and_plot(tmp_path, capsys):
    from reflow_plugin import report

    _fake_logged_run(tmp_path / "a" / "baseline", [(10.0, 20.0), (30.0, 24.0)], rss=500, ms=10.0)
    _fake_logged_run(tmp_path / "b" / "baseline", [(20.0, 22.0), (50.0, 26.0)], rss=700, ms=20.0)
    _fake_logged_run(tmp_path / "a" / "ours", [(15.0, 21.0), (45.0, 27.0)], rss=600, ms=10.0, timed=False)
    assert report.main([str(tmp_path)]) == 0
    table = (tmp_path / "cost.md").read_text().splitlines()
    assert table[2] == "| baseline | 2 | 40 | 80 | 600 | 75.0 | 1.00 | 25.00 |"  # means over scenes a and b
    assert (tmp_path / "accuracy_vs_time.png").stat().st_size > 1000
    assert "a/ours has no timed test events" in capsys.readouterr().err
    assert report.main([str(tmp_path / "empty")]) == 2


def test_pareto_front_and_table(tmp_path):
    from reflow_plugin import report

    points = {"slow_good": (100.0, 28.0), "fast_bad": (10.0, 20.0), "dominated": (120.0, 27.0),
              "tie_slower": (100.0, 27.5), "middle": (50.0, 25.0)}
    assert report.pareto_front(points) == ["fast_bad", "middle", "slow_good"]
    _fake_logged_run(tmp_path / "s" / "cheap", [(5.0, 18.0), (10.0, 21.0)], rss=500, ms=10.0)
    _fake_logged_run(tmp_path / "s" / "costly", [(40.0, 22.0), (80.0, 20.5)], rss=500, ms=10.0)
    assert report.main([str(tmp_path), "--pareto"]) == 0
    lines = (tmp_path / "pareto.md").read_text().splitlines()
    assert lines[2:] == ["| s | cheap | 10 | 21.00 | * |", "| s | costly | 80 | 20.50 |  |"]


def test_sweep_variants_change_one_knob_each(tmp_path):
    from reflow_plugin.ablate import plan
    from reflow_plugin.sweep import VARIANTS

    specs = plan([("skating", tmp_path)], list(VARIANTS), tmp_path / "out", [], table=VARIANTS)
    commands = {s.row: list(s.command) for s in specs}
    for name, command in commands.items():
        reference = commands["reflow" if name.startswith("reflow") else "baseline"]
        added = [a for a in command if a not in reference]
        assert (added == []) == (name in ("reflow", "baseline")), (name, added)
    assert "--flow_every" in commands["reflow_flow_every"] and "-r" in commands["baseline_resolution"]


def test_parallel_local_jobs_share_the_cpus(monkeypatch):
    from reflow_plugin import ablate

    monkeypatch.setattr(ablate, "available_cpus", lambda: 8)
    env: dict[str, str] = {}
    assert ablate.share_threads(env, 3, "local") == "2" and env == {"OMP_NUM_THREADS": "2"}
    assert ablate.share_threads({}, 16, "local") == "1"  # never 0
    for environ, jobs, executor in (({}, 1, "local"), ({}, 4, "slurm"), ({"OMP_NUM_THREADS": "4"}, 2, "local")):
        before = dict(environ)
        assert ablate.share_threads(environ, jobs, executor) is None and environ == before
