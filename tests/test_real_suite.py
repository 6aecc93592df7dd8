"""benchmarks/real_suite.py + real_captures.py: registry, missing-capture error, extraction, resume, in-mask PSNR."""
from __future__ import annotations

import json
import os
import math
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from baselines.run_folder import read_run_record
from benchmarks import real_captures, real_suite
from benchmarks.real_captures import CAPTURES, Capture, CaptureError


def test_registry_pins_every_capture_to_a_commit_and_a_known_family():
    for name, capture in CAPTURES.items():
        assert name == capture.name
        assert re.fullmatch(r"[0-9a-f]{40}", capture.commit), name
        assert capture.family in real_captures.FAMILIES, name
        assert re.fullmatch(r"[\w.-]+/[\w.-]+", capture.repo), name
        assert bool(capture.keep) == (capture.family in ("nvidia", "panoptic")), name  # they copy named entries only


def test_missing_capture_stops_before_training_naming_repository_commit_and_setup(tmp_path, capsys):
    code = real_suite.main(["--captures", "nvidia_balloon1", "--data", str(tmp_path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    capture = CAPTURES["nvidia_balloon1"]
    assert code == 2
    assert err.startswith("error: capture(s) not found: nvidia_balloon1")
    assert capture.repo in err and capture.commit in err and "--setup nvidia_balloon1" in err
    assert not (tmp_path / "out").exists()  # nothing trained, nothing written


def test_unknown_capture_and_method_are_one_line_errors(tmp_path, capsys):
    assert real_suite.main(["--captures", "nope", "--data", str(tmp_path)]) == 2
    assert "unknown capture(s) ['nope']" in capsys.readouterr().err
    assert real_suite.main(["--methods", "reflow,fancy", "--data", str(tmp_path)]) == 2
    assert "unknown method(s) ['fancy']" in capsys.readouterr().err


def test_fetch_instructions_print_clone_and_setup_lines(tmp_path, capsys):
    assert real_suite.main(["--fetch-instructions", "--captures", "davis_lady_running", "--data", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "git clone https://github.com/Junyi42/monst3r" in out
    assert "--setup davis_lady_running --clone " in out and str(tmp_path) in out


@pytest.fixture
def source_repo(tmp_path) -> tuple[Path, str]:
    """A git repository with an NVIDIA-layout folder plus files the capture does not keep."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    repo = tmp_path / "repo"
    scene = repo / "Scene"
    (scene / "images").mkdir(parents=True)
    (scene / "disp").mkdir()
    (scene / "flow").mkdir()
    cv2.imwrite(str(scene / "images" / "000.png"), np.full((4, 6, 3), 7, np.uint8))
    np.save(scene / "disp" / "000.npy", np.ones((4, 6), np.float32))
    np.save(scene / "poses_bounds.npy", np.zeros((1, 17)))
    (scene / "flow" / "000_fwd.npz").write_bytes(b"not kept")
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "data"], check=True)
    commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    return repo, commit


def test_extract_copies_only_the_kept_entries_at_the_pinned_commit(source_repo, tmp_path):
    repo, commit = source_repo
    target = tmp_path / "data" / "scene"
    written = real_captures.extract(repo, commit, "Scene", target, ("images", "disp", "poses_bounds.npy"))
    assert written == 3
    assert sorted(p.relative_to(target).as_posix() for p in target.rglob("*") if p.is_file()) == [
        "disp/000.npy", "images/000.png", "poses_bounds.npy"]
    assert (cv2.imread(str(target / "images" / "000.png")) == 7).all()
    capture = Capture(name="scene", family="nvidia", repo="o/r", commit=commit, folder="Scene", what="", keep=("images",))
    assert not real_captures.is_ready(capture, tmp_path / "empty")
    assert real_captures.is_ready(capture, tmp_path / "data")


def test_extract_names_what_is_missing(source_repo, tmp_path):
    repo, commit = source_repo
    with pytest.raises(CaptureError, match="failed in"):
        real_captures.extract(repo, commit, "Scene", tmp_path / "t", ("images", "motion_masks"))
    with pytest.raises(CaptureError, match="does not exist"):
        real_captures.extract(tmp_path / "nowhere", commit, "Scene", tmp_path / "t")


def test_region_psnr_counts_only_the_region():
    gt = np.zeros((4, 4, 3), np.uint8)
    render = gt.copy()
    render[:2] = 10                                        # error 10 on the top half only
    top = np.zeros((4, 4), bool)
    top[:2] = True
    assert real_suite.region_psnr(render, gt, top) == pytest.approx(10 * math.log10(255 ** 2 / 100))
    assert real_suite.region_psnr(render, gt, ~top) == math.inf
    assert real_suite.region_psnr(render, gt, np.zeros((4, 4), bool)) is None


def _fake_run(run: Path, renders: list[np.ndarray], gts: list[np.ndarray]) -> None:
    for sub, images in (("renders", renders), ("gt", gts)):
        folder = run / "test" / "ours_10" / sub
        folder.mkdir(parents=True, exist_ok=True)
        for i, image in enumerate(images):
            cv2.imwrite(str(folder / f"{i:05d}.png"), image)


def test_masked_metrics_average_over_views_and_check_shapes(tmp_path):
    gt = np.zeros((4, 4, 3), np.uint8)
    inside_error = gt.copy()
    inside_error[0, 0] = 255                               # wrong only inside the mask
    mask = np.zeros((4, 4), bool)
    mask[0, 0] = True
    _fake_run(tmp_path / "run", [inside_error, gt], [gt, gt])
    metrics = real_suite.masked_metrics(tmp_path / "run", [mask, mask])
    assert metrics["PSNR-mask"] == math.inf                # mean of 0 dB (view 1) and inf (view 2)
    only_first = real_suite.masked_metrics(tmp_path / "run", [mask, np.zeros((4, 4), bool)])
    assert only_first["PSNR-mask"] == pytest.approx(0.0)  # view 2 has no masked pixel: left out
    assert only_first["PSNR-outside"] == math.inf
    with pytest.raises(real_suite.SuiteError, match="mask"):
        real_suite.masked_metrics(tmp_path / "run", [np.zeros((2, 2), bool)] * 2)


def test_masked_metrics_refuse_renders_of_another_split(tmp_path):
    """Masks pair with the numbered renders by position: a render folder of other views (a capture
    prepared again, another hold-out) is refused, by the run's views.json where it has one, by
    the count of renders otherwise."""
    gt = np.zeros((4, 4, 3), np.uint8)
    mask = np.zeros((4, 4), bool)
    _fake_run(tmp_path / "run", [gt, gt], [gt, gt])
    with pytest.raises(real_suite.SuiteError, match="2 rendered views for 3 held-out views"):
        real_suite.masked_metrics(tmp_path / "run", [mask] * 3)
    views = tmp_path / "run" / "test" / "ours_10" / "views.json"
    views.write_text(json.dumps({"00000.png": "00000", "00001.png": "00008"}))
    assert real_suite.masked_metrics(tmp_path / "run", [mask] * 2, ["00000", "00008"])["PSNR-outside"] == math.inf
    with pytest.raises(real_suite.SuiteError, match="00001.png renders '00008', the held-out view with this mask is '00007'"):
        real_suite.masked_metrics(tmp_path / "run", [mask] * 2, ["00000", "00007"])


def test_evaluation_records_which_view_each_png_is(tmp_path):
    import torch

    from baselines.data.cameras import Camera
    from baselines.fourdgs.evaluate import VIEWS_FILE, evaluate_cameras
    from tests._model_helpers import make_model

    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[16.0, 0, 8.0], [0, 16.0, 8.0], [0, 0, 1]])
    cameras = [Camera(uid=k, image_name=name, width=16, height=16, K=K, viewmat=viewmat, time=0.5,
                      image=torch.zeros(16, 16, 3)) for k, name in enumerate(("00003", "00011"))]
    evaluate_cameras(make_model(40), cameras, "coarse", torch.zeros(3), "reference", out_dir=tmp_path)
    assert json.loads((tmp_path / VIEWS_FILE).read_text()) == {"00000.png": cameras[0].image_name,
                                                               "00001.png": cameras[1].image_name}


def test_run_one_redoes_a_torn_run_and_refuses_a_run_of_another_command(tmp_path, monkeypatch):
    capture = CAPTURES["nvidia_balloon1"]
    schedule = {"coarse_iterations": 3, "iterations": 5, "seed": 0}
    calls = []

    def fake_train(command, **kwargs):
        calls.append(command)
        return subprocess.CompletedProcess(command, 0)

    monkeypatch.setattr(real_suite.subprocess, "run", fake_train)
    monkeypatch.setattr(real_suite, "code_version", lambda: "abc")
    torn = tmp_path / "out" / capture.name / "baseline"
    torn.mkdir(parents=True)
    (torn / "leftover.txt").write_text("from a killed run")
    run = real_suite.run_one(capture, "baseline", tmp_path, tmp_path / "out", schedule, [], 1)
    assert run == torn and len(calls) == 1 and not (torn / "leftover.txt").exists()
    assert json.loads((torn / real_suite.DONE_FILE).read_text())["code"] == "abc"
    real_suite.run_one(capture, "baseline", tmp_path, tmp_path / "out", schedule, [], 1)
    assert len(calls) == 1                                 # done: reused, not retrained
    with pytest.raises(real_suite.SuiteError, match="another command"):
        real_suite.run_one(capture, "baseline", tmp_path, tmp_path / "out", dict(schedule, iterations=6), [], 1)


def _write_ply(path: Path, points: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    records = np.zeros(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    for k, name in enumerate("xyz"):
        records[name] = points[:, k]
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(records, "vertex")]).write(str(path))


def test_canonical_check_tells_a_cloud_at_scene_depth_from_one_collapsed_at_the_camera(tmp_path):
    import torch
    from types import SimpleNamespace

    from baselines.data import Camera

    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    camera = Camera(uid=0, image_name="0", width=64, height=48, K=K, viewmat=torch.eye(4), time=0.0)
    scene = SimpleNamespace(train_cameras=[camera], point_cloud=None, near_far=(40.0, 60.0))
    rng = np.random.default_rng(0)
    at_depth = np.column_stack([rng.uniform(-10, 10, 500), rng.uniform(-8, 8, 500), rng.uniform(45, 52, 500)])
    _write_ply(tmp_path / "good" / "reflow" / "static.ply", at_depth)
    _write_ply(tmp_path / "good" / "reflow" / "dynamic.ply", at_depth[:50])
    good = real_suite.canonical_check(tmp_path / "good", scene)
    assert good["reference"] == "bounds" and good["reference_depth"] == pytest.approx(math.sqrt(40 * 60))
    assert good["static depth / scene depth"] == pytest.approx(np.median(at_depth[:, 2]) / math.sqrt(2400), rel=0.05)
    assert good["static in view %"] > 90 and good["dynamic spread"] > 0.05
    collapsed = at_depth * 1e-5                             # 1 / raw disparity: everything at the camera centre
    _write_ply(tmp_path / "bad" / "reflow" / "static.ply", collapsed)
    _write_ply(tmp_path / "bad" / "reflow" / "dynamic.ply", np.repeat(collapsed[:1], 50, 0))
    bad = real_suite.canonical_check(tmp_path / "bad", scene)
    assert bad["static depth / scene depth"] < 1e-4
    assert bad["static in view %"] == 0.0                   # in front of the camera but before the near plane
    assert bad["dynamic spread"] == pytest.approx(0.0, abs=1e-9)
    assert real_suite.canonical_check(tmp_path / "baseline_run", scene) is None


def test_run_one_leaves_a_run_that_another_process_is_training_alone(tmp_path, monkeypatch):
    capture = CAPTURES["nvidia_balloon1"]
    running = tmp_path / "out" / capture.name / "reflow"
    running.mkdir(parents=True)
    (running / "train_log.jsonl").write_text("")
    (running.parent / "reflow.lock").write_text(str(os.getppid()))   # a live process: our parent
    monkeypatch.setattr(real_suite.subprocess, "run", lambda *a, **k: pytest.fail("must not train"))
    with pytest.raises(real_suite.SuiteError, match="being trained by process"):
        real_suite.run_one(capture, "reflow", tmp_path, tmp_path / "out", {"coarse_iterations": 1, "iterations": 2,
                                                                           "seed": 0}, [], 1)
    assert (running / "train_log.jsonl").exists()


def test_a_failed_training_is_a_table_row_and_leaves_no_done_marker(tmp_path, monkeypatch):
    """One diverging run must not abort a sweep of hours: run_one raises TrainingFailed (the log's
    last lines), the table shows the row as FAILED, and the folder is redone next time."""
    capture = CAPTURES["nvidia_balloon1"]
    schedule = {"coarse_iterations": 3, "iterations": 5, "seed": 0}

    def failing_train(command, stdout=None, **kwargs):
        stdout.write("[train] plugin reflow\nerror: features contains NaN or inf\n")
        return subprocess.CompletedProcess(command, 2)

    monkeypatch.setattr(real_suite.subprocess, "run", failing_train)
    monkeypatch.setattr(real_suite, "code_version", lambda: "abc")
    with pytest.raises(real_suite.TrainingFailed, match="exited 2: error: features contains NaN or inf .log: ") as info:
        real_suite.run_one(capture, "reflow", tmp_path, tmp_path / "out", schedule, [], 1)
    assert "[train] plugin reflow" not in str(info.value)          # the error line, not the log's tail
    run = tmp_path / "out" / capture.name / "reflow"
    assert not (run / real_suite.DONE_FILE).exists() and not (run.parent / "reflow.lock").exists()
    text = real_suite.table({capture.name: {"baseline": {"PSNR": 20.0, "SSIM": 0.5},
                                            "reflow": {"failed": "train.py exited 2: a | b"}}})
    failed = [line for line in text.splitlines() if "| reflow |" in line][0]
    assert "FAILED: train.py exited 2: a / b" in failed
    assert failed.count("|") == text.splitlines()[0].count("|")   # as many cells as the header


def _tiny_capture(tiny_scene: Path, root: Path) -> Capture:
    """A registry-like capture whose dataset is the simulator's tiny NVIDIA-layout scene."""
    (root / "data").mkdir(parents=True)
    (root / "data" / "tiny").symlink_to(tiny_scene)
    return Capture(name="tiny", family="nvidia", repo="x/y", commit="0" * 40, folder=".", what="tiny", resolution=1)


def test_a_chunked_run_resumes_from_its_checkpoint_and_ends_as_an_uninterrupted_one(tiny_scene, tmp_path):
    """--chunk-seconds: the first call is stopped (SIGTERM -> checkpoint) at its first logged
    iteration, the second continues from that checkpoint; densification runs across the cut. The
    result equals one uninterrupted run (the trainer's exact-resume guarantee: RNG, sampler and
    optimizer state are in the checkpoint)."""
    from plyfile import PlyData

    capture = _tiny_capture(tiny_scene, tmp_path)
    schedule = {"coarse_iterations": 10, "iterations": 50, "seed": 0}
    extra = ["--configs", str(real_suite.ROOT / "arguments" / "synthetic" / "default.py"), "--log_every", "1",
             "--densify_from_iter", "5", "--densification_interval", "10", "--densify_until_iter", "40",
             "--pruning_from_iter", "5", "--pruning_interval", "10", "--position_lr_max_steps", "50"]
    args = (capture, "baseline", tmp_path / "data")
    whole = real_suite.run_one(*args, tmp_path / "whole", schedule, extra, 1)
    with pytest.raises(real_suite.ChunkPending, match="call again"):
        real_suite.run_one(*args, tmp_path / "chunked", schedule, extra, 1, chunk_seconds=0)
    run = tmp_path / "chunked" / "tiny" / "baseline"
    assert not (run / real_suite.DONE_FILE).exists() and real_suite.latest_checkpoint(run) is not None
    assert real_suite.run_one(*args, tmp_path / "chunked", schedule, extra, 1, chunk_seconds=1e6) == run
    chunks = json.loads((run / real_suite.CHUNKS_FILE).read_text())["chunks"]
    assert [c["returncode"] for c in chunks] == [real_suite.INTERRUPTED_RC, 0] and chunks[1]["from"]
    logged = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    resumed = next(k for k, e in enumerate(logged) if e["kind"] == "resumed")
    counts = {e["num_gaussians"] for e in logged[resumed:] if e["kind"] == "iter"}
    assert len(counts) > 1, counts  # densification and pruning changed the count after the cut
    # bookkeeping, not speed: the resumed chunk starts its clock at the checkpoint's
    cut = next(e for e in logged if e["kind"] == "interrupted")
    end = next(e for e in logged if e["kind"] == "train_end")
    assert logged[resumed]["clock_restored"]
    assert logged[resumed]["train_cpu_seconds"] == cut["train_cpu_seconds"]
    assert real_suite.train_cpu_seconds(logged) == end["train_cpu_seconds"]
    old_checkpoint = [{**e, "clock_restored": False} if e["kind"] == "resumed" else e for e in logged]
    assert real_suite.train_cpu_seconds(old_checkpoint) is None  # a chunk that restarted the clock: no total
    assert json.loads((run / real_suite.DONE_FILE).read_text())["command"] == \
        json.loads((whole / real_suite.DONE_FILE).read_text())["command"][:4] + \
        [str(run)] + json.loads((whole / real_suite.DONE_FILE).read_text())["command"][5:]
    ply = "point_cloud/iteration_50/point_cloud.ply"
    a, b = PlyData.read(str(whole / ply))["vertex"], PlyData.read(str(run / ply))["vertex"]
    assert a.count == b.count
    for name in ("x", "y", "z", "opacity", "f_dc_0"):
        np.testing.assert_allclose(np.asarray(b[name]), np.asarray(a[name]), rtol=1e-4, atol=1e-5, err_msg=name)
    psnr = [json.loads((r / "results.json").read_text())["ours_50"]["PSNR"] for r in (whole, run)]
    assert psnr[1] == pytest.approx(psnr[0], abs=1e-3)
    summary = real_suite.summarise(run, [], None)
    assert summary["train_s"] == pytest.approx(sum(c["seconds"] for c in chunks))
    assert summary["train_cpu_s"] == end["train_cpu_seconds"]
    # the MLP arithmetic the run trained with (run.json's machine record) is in its table row
    assert summary["MLP"] == read_run_record(run)["machine"]["mlp_arithmetic"] in ("float32", "bfloat16")
    assert f"| {summary['MLP']} |" in real_suite.table({"toy": {"baseline": summary}})


def test_run_chunked_skips_done_runs_and_stops_when_the_call_s_time_is_spent():
    order = []

    def train(job, left):
        order.append((job, left > 0))
        if job == "b":
            raise real_suite.ChunkPending("b: call again")
        return Path(job)

    with pytest.raises(real_suite.ChunkPending, match="b: call again"):
        real_suite.run_chunked(["a", "b", "c"], 100.0, train)
    assert order == [("a", True), ("b", True)]                    # c not started in this call
    with pytest.raises(real_suite.ChunkPending, match="3 run"):
        real_suite.run_chunked(["a", "b", "c"], 0.0, train)        # no time left: nothing starts
    assert real_suite.run_chunked(["a", "c"], 100.0, train) == [Path("a"), Path("c")]


def test_run_chunked_with_workers_trains_runs_at_once_and_reports_a_stopped_one():
    """workers=2: two runs train at the same time (each waits for the other at a barrier, which a
    one-at-a-time loop would never reach); a stopped run makes the call pending, the others finish."""
    import threading
    met = threading.Barrier(2, timeout=10)

    def train(job, left):
        if job in ("a", "b"):
            met.wait()
        if job == "b":
            raise real_suite.ChunkPending("b: call again")
        return Path(job)

    finished = []
    with pytest.raises(real_suite.ChunkPending, match="b: call again"):
        real_suite.run_chunked(["a", "b", "c"], 100.0, lambda job, left: finished.append(job) or train(job, left),
                               workers=2)
    assert sorted(finished) == ["a", "b", "c"]  # a's worker went on to c
    assert real_suite.run_chunked(["a", "c", "d"], 100.0, lambda job, left: Path(job), workers=3) == [
        Path("a"), Path("c"), Path("d")]                                   # in the jobs' order


@pytest.mark.parametrize("workers", [1, 2])
def test_run_chunked_raises_a_run_s_error_instead_of_calling_the_call_pending(workers):
    """A folder that refuses its run (SuiteError) is an error, not 'call again' (exit 3), which a
    loop repeating pending calls would retry for ever."""
    def train(job, left):
        if job == "b":
            raise real_suite.SuiteError("b was started with another command")
        return Path(job)

    with pytest.raises(real_suite.SuiteError, match="another command"):
        real_suite.run_chunked(["a", "b", "c"], 100.0, train, workers=workers)


def test_a_chunked_run_is_continued_only_with_its_own_command_and_code(tmp_path, monkeypatch):
    capture = CAPTURES["nvidia_balloon1"]
    schedule = {"coarse_iterations": 3, "iterations": 5, "seed": 0}
    run = tmp_path / "out" / capture.name / "baseline"
    command = real_suite.train_command(capture, "baseline", tmp_path / capture.name, run, schedule, [])
    run.mkdir(parents=True)
    (run / "chkpnt_coarse_3.pth").write_bytes(b"")
    (run / "chkpnt_fine_2.pth").write_bytes(b"")
    (run / real_suite.CHUNKS_FILE).write_text(json.dumps({"command": command, "code": "abc", "chunks": []}))
    assert real_suite.latest_checkpoint(run).name == "chkpnt_fine_2.pth"        # fine after coarse
    monkeypatch.setattr(real_suite.subprocess, "Popen", lambda *a, **k: pytest.fail("must not train"))
    monkeypatch.setattr(real_suite, "code_version", lambda: "def")
    with pytest.raises(real_suite.SuiteError, match="started with code abc"):
        real_suite.run_one(capture, "baseline", tmp_path, tmp_path / "out", schedule, [], 1, chunk_seconds=10)
    monkeypatch.setattr(real_suite, "code_version", lambda: "abc")
    with pytest.raises(real_suite.SuiteError, match="started with another command"):
        real_suite.run_one(capture, "baseline", tmp_path, tmp_path / "out", dict(schedule, iterations=6), [], 1,
                           chunk_seconds=10)
    assert (run / "chkpnt_fine_2.pth").exists()                               # nothing was cleared


def test_side_by_side_columns_are_titled_by_method(tmp_path, monkeypatch):
    # convergence runs all live in folders named fine_<budget>: the titles must be the methods
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts"))
    import side_by_side as tool

    runs = {}
    for method, value in (("baseline", 40), ("reflow", 200)):
        run = tmp_path / method / "fine_3000"
        for kind, image_value in (("gt", 90), ("renders", value)):
            folder = run / "test" / "ours_3000" / kind
            folder.mkdir(parents=True)
            for view in range(3):
                cv2.imwrite(str(folder / f"{view:05d}.png"), np.full((9, 16, 3), image_value, np.uint8))
        runs[method] = run
    titles = []
    monkeypatch.setattr(tool, "label", lambda image, text: titles.append(text) or image)
    masks = [np.zeros((9, 16), bool) for _ in range(3)]
    masks[2][:4] = True
    capture = real_suite.CAPTURES["davis_libby"]
    output = real_suite.side_by_side(capture, runs, masks, tmp_path / "images")
    assert output.is_file() and cv2.imread(str(output)).shape == (2 * 9 * 20, 3 * 16 * 20, 3)
    assert titles == ["ground truth", "baseline", "reflow"] * 2
    with pytest.raises(SystemExit):
        tool.main([str(runs["baseline"]), "--labels", "a", "b", "-o", str(tmp_path / "x.png")])
