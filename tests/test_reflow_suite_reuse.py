"""benchmarks/reflow_suite.py reuses a finished run only when it was trained with the same command."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from benchmarks import reflow_suite
from benchmarks.reflow_suite import METHODS, SCHEDULES, SuiteError, check_scene_data, run_one, scene_source


def _finished_run(out: Path, scene: str, method: str, command: list[str]) -> Path:
    """A run folder as train.py and reflow_plugin.evaluate leave it (metrics, flow metrics, run.json)."""
    run = out / scene / method
    run.mkdir(parents=True)
    (run / "results.json").write_text(json.dumps({"ours_500": {"PSNR": 20.0, "SSIM": 0.5}}))
    (run / "flow_metrics.json").write_text(json.dumps({"ours_500": {"available": False}}))
    (run / "run.json").write_text(json.dumps({"state": "finished", "command": command}))
    return run


def _command(scene: str, method: str, out: Path, extra: list[str]) -> list[str]:
    source, _ = scene_source(scene, "exact")
    return ["train.py", "-s", str(source), "-m", str(out / scene / method), "--quiet", "--overwrite",
            *METHODS[method], *extra]


def test_a_finished_run_of_another_schedule_stops_the_suite_and_the_same_one_is_reused(tmp_path, monkeypatch):
    monkeypatch.setattr(reflow_suite.subprocess, "run", lambda *a, **k: pytest.fail(f"nothing may run: {a}"))
    quarter = SCHEDULES["quarter"]
    run = _finished_run(tmp_path, "skating", "reflow", _command("skating", "reflow", tmp_path, quarter))
    assert run_one("skating", "reflow", tmp_path, quarter, None) == run  # same command: reused as it is
    with pytest.raises(SuiteError, match="trained with another command"):
        run_one("skating", "reflow", tmp_path, SCHEDULES["half"], None)
    assert run_one("skating", "reflow", tmp_path, SCHEDULES["half"], None, reuse_any=True) == run  # --report_only
    # through the command line: one error line, exit status 2
    monkeypatch.setattr(sys, "argv", ["reflow_suite.py"])
    with pytest.raises(SystemExit) as stop:
        reflow_suite.main(["--scenes", "skating", "--methods", "reflow", "--out", str(tmp_path), "--schedule", "half"])
    assert stop.value.code == 2


def test_a_real_priors_scene_written_at_another_scale_is_refused(tmp_path):
    (tmp_path / "scene.json").write_text(json.dumps({"scene_scale": 50.0}))
    check_scene_data(tmp_path, "real", 50.0)
    with pytest.raises(SuiteError, match="--scene_scale 50.0, not 10"):
        check_scene_data(tmp_path, "real", 10.0)
    check_scene_data(tmp_path, "exact", 10.0)  # the exact priors have no scale flag
