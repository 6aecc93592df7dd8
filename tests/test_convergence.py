"""benchmarks/convergence.py: the schedule scaling rule, the run folders, and the table/plot on fake results."""
from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from arguments.config import read_config_chain
from arguments.params import OptimizationParams
from benchmarks import convergence, real_suite
from benchmarks.real_captures import CAPTURES, CaptureError

ROOT = Path(__file__).resolve().parent.parent
# iteration-valued OptimizationParams fields the rule leaves alone on purpose (module docstring)
NOT_SCALED = {"iterations", "coarse_iterations", "stall_iterations", "weight_decay_iteration"}


def _family_schedule(config: str) -> dict:
    """OptimizationParams' defaults with the config chain of `config` applied."""
    values = {f.name: f.default for f in dataclasses.fields(OptimizationParams)}
    for _, raw in read_config_chain(ROOT / config):
        values.update(raw.get("OptimizationParams", {}))
    return values


@pytest.mark.parametrize("config", ["arguments/nvidia/default.py", "arguments/hypernerf/default.py"])
def test_full_schedule_is_the_family_configs(config):
    family = _family_schedule(config)
    assert family["iterations"] == convergence.FULL_BUDGET
    assert {name: family[name] for name in convergence.FULL_SCHEDULE} == convergence.FULL_SCHEDULE


def test_every_iteration_valued_field_is_scaled_or_left_alone_on_purpose():
    """A new schedule field (…_iter, …_interval, …_steps, …iteration(s)) must be decided here."""
    names = {f.name for f in dataclasses.fields(OptimizationParams)
             if f.name.endswith(("_iter", "_interval", "_steps", "iteration", "iterations"))}
    assert names == set(convergence.FULL_SCHEDULE) | NOT_SCALED


def test_schedule_scales_proportionally_with_a_floor_on_the_intervals():
    assert convergence.scaled_schedule(14_000) == convergence.FULL_SCHEDULE
    half = convergence.scaled_schedule(7000)
    assert half == {"densify_from_iter": 250, "densify_until_iter": 5000, "pruning_from_iter": 250,
                    "densification_interval": 50, "pruning_interval": 50, "opacity_reset_interval": 150_000,
                    "position_lr_max_steps": 10_000}
    small = convergence.scaled_schedule(500)
    assert small["densify_from_iter"] == 18 and small["densify_until_iter"] == 357
    assert small["densification_interval"] == small["pruning_interval"] == 10      # floor, not 4
    assert small["opacity_reset_interval"] > 500                                    # still no reset in the run
    assert convergence.scaled_schedule(1)["densify_from_iter"] == 1
    with pytest.raises(ValueError):
        convergence.scaled_schedule(0)


def test_schedule_flags_are_accepted_by_train_py_and_land_in_the_options():
    from arguments.cli import parse_train_args

    args = parse_train_args(["-s", "x", *convergence.schedule_flags(3000)])
    for name, value in convergence.scaled_schedule(3000).items():
        assert getattr(args.opt, name) == value, name


def test_runs_are_one_folder_per_budget_and_a_done_budget_is_not_retrained(tmp_path, monkeypatch):
    capture = CAPTURES["nvidia_balloon1"]
    calls = []

    def fake_train(command, **kwargs):
        calls.append(command)
        return subprocess.CompletedProcess(command, 0)

    monkeypatch.setattr(real_suite.subprocess, "run", fake_train)
    monkeypatch.setattr(real_suite, "code_version", lambda: "abc")
    for budget in (100, 300, 100):
        run = convergence.run_folder(tmp_path / "out", capture.name, "baseline", budget)
        schedule = {"coarse_iterations": 10, "iterations": budget, "seed": 0}
        assert real_suite.run_one(capture, "baseline", tmp_path, tmp_path / "out", schedule,
                                  convergence.schedule_flags(budget), 1, run=run) == run
    assert len(calls) == 2                                             # the second 100 was done
    assert "--densify_until_iter" in calls[1] and calls[1][calls[1].index("--iterations") + 1] == "300"
    assert (tmp_path / "out" / capture.name / "baseline" / "fine_300" / real_suite.DONE_FILE).is_file()
    assert not list((tmp_path / "out" / capture.name / "baseline").glob("*.lock"))


def test_final_gaussians_is_the_last_fine_iteration_record(tmp_path):
    records = [{"kind": "iter", "stage": "coarse", "iteration": 10, "num_gaussians": 5},
               {"kind": "iter", "stage": "fine", "iteration": 10, "num_gaussians": 7},
               {"kind": "test", "stage": "fine", "iteration": 20},
               {"kind": "iter", "stage": "fine", "iteration": 20, "num_gaussians": 9}]
    (tmp_path / "train_log.jsonl").write_text("\n".join(json.dumps(r) for r in records) + "\n")
    assert convergence.final_gaussians(tmp_path) == 9


def _fake_rows() -> list[dict]:
    rows = []
    for capture in ("cap_b", "cap_a"):
        for method, offset in (("reflow", 1.0), ("baseline", 0.0)):
            for budget in (4000, 500, 1500):
                rows.append({"capture": capture, "method": method, "budget": budget, "PSNR": 20 + offset + budget / 1000,
                             "PSNR-mask": 15.0 + offset, "PSNR-outside": 22.0, "SSIM": 0.6, "Gaussians": 1000 * budget,
                             "train_s": budget / 10, "train_cpu_s": budget / 20 if capture == "cap_a" else None,
                             "MLP": "float32" if capture == "cap_a" else None})
    rows[-1] = {"capture": "cap_a", "method": "baseline", "budget": 1500, "failed": "train.py exited 2: a | b"}
    return rows


def test_table_orders_capture_method_budget_and_shows_a_failed_run():
    lines = convergence.table(_fake_rows()).splitlines()
    body = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines[2:]]
    assert [row[:3] for row in body[:3]] == [["cap_a", "baseline", "500"], ["cap_a", "baseline", "1500"],
                                             ["cap_a", "baseline", "4000"]]
    assert body[1][3] == "FAILED: train.py exited 2: a / b"
    assert all(line.count("|") == lines[0].count("|") for line in lines)
    assert body[0][3:] == ["20.50", "15.00", "22.00", "0.600", "500,000", "50", "25", "float32"]
    assert body[-1][-2:] == ["-", "-"]  # a run older than the training clock and run.json's machine record
    assert len(body) == 12


def test_plot_has_one_panel_per_capture(tmp_path):
    rows = _fake_rows()
    two = convergence.plot(rows, tmp_path / "two.png")
    one = convergence.plot([r for r in rows if r["capture"] == "cap_a"], tmp_path / "one.png")
    wide, narrow = cv2.imread(str(two)), cv2.imread(str(one))
    assert wide.shape[0] == narrow.shape[0] and wide.shape[1] == pytest.approx(2 * narrow.shape[1], rel=0.02)
    assert convergence.plot([rows[-1]], tmp_path / "none.png") is None            # nothing finished: no plot
    colours = wide.reshape(-1, 3).astype(int)
    red = ((colours[:, 2] > 180) & (colours[:, 1] < 80) & (colours[:, 0] < 80)).sum()
    assert red > 50                                                                 # ReFlow's curves are drawn


def test_bad_budgets_and_resolutions_are_one_line_errors(tmp_path, capsys):
    for argv in (["--budgets", "1k"], ["--budgets", "0,100"], ["--resolution", "nope=2"],
                 ["--resolution", "nvidia_balloon1=x"], ["--jobs", "0"], ["--downscale", "0"]):
        assert convergence.main([*argv, "--data", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()
    with pytest.raises(CaptureError):
        real_suite.parse_resolutions("nvidia_balloon1=0", [CAPTURES["nvidia_balloon1"]])
    assert real_suite.parse_resolutions("panoptic_basketball=4,nvidia_balloon1=8",
                                         [CAPTURES["nvidia_balloon1"]]) == {"nvidia_balloon1": 8}


def test_downscale_multiplies_the_registry_resolution_and_a_named_one_wins():
    captures = [CAPTURES["nvidia_balloon1"], CAPTURES["panoptic_basketball"], CAPTURES["davis_dog"]]
    chosen = {c.name: c.resolution for c in convergence.with_resolutions(captures, 2, "davis_dog=3")}
    assert chosen == {"nvidia_balloon1": 2 * CAPTURES["nvidia_balloon1"].resolution,
                      "panoptic_basketball": 2 * CAPTURES["panoptic_basketball"].resolution, "davis_dog": 3}
    assert [c.resolution for c in convergence.with_resolutions(captures, 1, None)] == [c.resolution for c in captures]
    with pytest.raises(CaptureError):
        convergence.with_resolutions(captures, 0, None)


def test_downscale_refuses_a_product_that_train_py_reads_as_a_width():
    """train.py -r 1, 2, 4, 8 divides the image size; any other value is a width in pixels. Before,
    --downscale 3 gave Balloon1 (-r 4) -r 12: 12 px wide images, trained without a word."""
    balloon, dog = CAPTURES["nvidia_balloon1"], CAPTURES["davis_dog"]
    with pytest.raises(CaptureError, match=r"nvidia_balloon1's -r 4 x 3 = 12 is no downscale factor"):
        convergence.with_resolutions([balloon], 3, None)
    with pytest.raises(CaptureError, match="davis_dog's -r 1 x 3 = 3"):
        convergence.with_resolutions([dog], 3, None)
    assert [c.resolution for c in convergence.with_resolutions([balloon, dog], 2, None)] == [8, 2]
    # a capture set by name is the user's explicit -r: not checked against the factor rule
    assert [c.resolution for c in convergence.with_resolutions([balloon, dog], 4, "nvidia_balloon1=160")] == [160, 4]


@pytest.mark.parametrize("main", [convergence.main, real_suite.main])
@pytest.mark.parametrize("argv", [["--chunk-seconds", "0"], ["--chunk-seconds", "-5"], ["--jobs", "0"], ["--methods", ","],
                                  ["--methods", "baseline,reflw"]])
def test_chunk_seconds_and_jobs_that_cannot_train_are_one_line_errors(tmp_path, capsys, main, argv):
    """--chunk-seconds 0 made every call exit 3 ('call again') at once, forever; real_suite.py took
    --jobs 0 (convergence.py refused it); --methods naming none printed an empty table and exit 0."""
    assert main([*argv, "--data", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and argv[0] in err, err
    assert not (tmp_path / "out").exists()
