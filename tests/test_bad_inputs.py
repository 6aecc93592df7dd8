"""Bad inputs through the public command lines, each in a subprocess (issues 25 and 41).

Every case must end with exit code 2, exactly one line containing ``error:``, no traceback, and
the output folder untouched (or absent). Cases run two at a time (each subprocess pays the torch
import, ~2-3 s on a quiet 2-core machine). ``REFLOW_BAD_INPUTS_ROOT=/path/to/checkout`` runs the
same table against another checkout (used to count how many cases an older version got right).
Ctrl-C and SIGTERM (exit 130 / 143, one line) and two trainings started together on one folder have
their own tests at the end.
"""
from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
import torch

ROOT = Path(os.environ.get("REFLOW_BAD_INPUTS_ROOT", Path(__file__).resolve().parents[1]))
CONFIG = str(ROOT / "arguments" / "synthetic" / "default.py")
SHORT = ["--configs", CONFIG, "--coarse_iterations", "1", "--iterations", "1", "--quiet", "--no-eval"]


@dataclass
class Case:
    name: str
    make: Callable[[Path, Path], list[str]]  # (scene copy, work dir) -> the command's argv after python
    expect: str  # a fragment of the error line
    output: str = "out"  # the folder (under the work dir) that must stay untouched or absent
    limit_file_size: int | None = None  # RLIMIT_FSIZE in bytes (a full disk, without root)
    untouched: bool = True  # False: the folder may hold the failed run's record, but no torn iteration
    extra: dict = field(default_factory=dict)


def _train(*args: str) -> list[str]:
    return [str(ROOT / "train.py"), *args]


def _fake_finished_run(folder: Path) -> None:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"RunParams": {"plugin": []}}))
    (folder / "run.json").write_text(json.dumps({"format": "reflow-4dgs/run", "version": 1, "state": "finished",
                                                 "plugins": [], "components": {}, "saved": []}))
    (folder / "point_cloud" / "iteration_7").mkdir(parents=True)
    (folder / "point_cloud" / "iteration_7" / "point_cloud.ply").write_bytes(b"ply\n")


def _reflow_checkpoint(path: Path) -> Path:
    torch.save({"format": "reflow-4dgs/training-state", "version": 1, "capture": (), "iteration": 20, "stage": "fine",
                "extra": {"run": {"plugins": ["reflow"], "components": {"reflow": ["full_flow"]}}}}, path)
    return path


def _transpose_first_mask(scene: Path) -> None:
    mask = sorted((scene / "motion_masks").iterdir())[0]
    image = cv2.imread(str(mask), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(mask), np.ascontiguousarray(np.pad(image, ((0, 16), (0, 0)))[:, :].T))


def _one_frame(scene: Path) -> None:
    np.save(scene / "poses_bounds.npy", np.load(scene / "poses_bounds.npy")[:1])
    for folder in ("images", "disp", "motion_masks"):
        for extra in sorted((scene / folder).iterdir())[1:]:
            extra.unlink()


_HELD_LOCKS: list = []  # locks this process holds for a case's subprocess (released at exit)


_TRAINED_LOCK = threading.Lock()
_TRAINED: dict[tuple[str, ...], Path] = {}  # extra flags -> the finished run the cases copy


def _trained(scene: Path, work: Path, *extra: str) -> Path:
    """A finished short run (fine iteration 1 saved, checkpointed) in work/first.

    Trained once per set of `extra` flags, in a subprocess, on its own copy of the first caller's
    scene (beside that caller's work folder), then copied for each case: the cases only read or
    break their copy, and each training subprocess costs a torch import and a save."""
    key = tuple(extra)
    with _TRAINED_LOCK:
        if key not in _TRAINED:
            template = work.parent / f"trained{len(_TRAINED)}"
            shutil.copytree(scene, template / "scene")
            env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
            subprocess.run([sys.executable, *_train("-s", str(template / "scene"), "-m", str(template / "run"), *SHORT,
                                                    "--checkpoint_iterations", "1", *extra)],
                           cwd=ROOT, env=env, check=True, capture_output=True, timeout=300)
            _TRAINED[key] = template / "run"
    run = work / "first"
    shutil.copytree(_TRAINED[key], run)
    return run


def _locked(folder: Path) -> Path:
    from baselines.run_folder import RunLock

    _HELD_LOCKS.append(RunLock(folder).acquire())
    return folder


def _garbage_run_json(scene: Path, work: Path) -> Path:
    run = _trained(scene, work)
    shutil.copytree(run / "point_cloud" / "iteration_1", run / "point_cloud" / "iteration_40")
    (run / "run.json").write_text((run / "run.json").read_text()[:40])
    return run


def _log_near_limit(scene: Path, work: Path, limit: int) -> Path:
    """A finished run whose train_log.jsonl ends 60 bytes short of `limit`: render.py's next log line
    crosses a file-size limit of `limit` bytes (a disk that fills up mid-line)."""
    run = _trained(scene, work)
    log = run / "train_log.jsonl"
    size = log.stat().st_size
    assert size < limit - 80, size
    pad = limit - 60 - size
    with open(log, "a") as handle:
        handle.write(json.dumps({"kind": "pad", "x": "p" * (pad - 25)}).ljust(pad - 1) + "\n")
    assert log.stat().st_size == limit - 60
    return run


def _without_extra_buffers(scene: Path, work: Path) -> Path:
    run = _trained(scene, work)
    (run / "point_cloud" / "iteration_1" / "extra_buffers.pth").unlink()
    return run


def _case_list() -> list[Case]:
    return [
        Case("-m is a file", lambda s, w: _train("-s", str(s), "-m", str(s / "poses_bounds.npy"), *SHORT),
             "is a file, not a folder", output="scene/poses_bounds.npy"),
        Case("-m cannot be created", lambda s, w: _train("-s", str(s), "-m", "/proc/no_such_dir/run", *SHORT),
             "cannot create /proc/no_such_dir"),
        Case("-m holds a finished run", lambda s, w: (_fake_finished_run(w / "out"),
                                                      _train("-s", str(s), "-m", str(w / "out"), *SHORT))[1],
             "already holds a finished run"),
        Case("garbage --start_checkpoint", lambda s, w: ((w / "junk.pth").write_bytes(os.urandom(3000)),
                                                         _train("-s", str(s), "-m", str(w / "out"), *SHORT,
                                                                "--start_checkpoint", str(w / "junk.pth")))[1],
             "junk.pth: cannot be read as a torch file"),
        Case("ReFlow checkpoint resumed as the baseline",
             lambda s, w: _train("-s", str(s), "-m", str(w / "out"), *SHORT, "--start_checkpoint",
                                 str(_reflow_checkpoint(w / "chkpnt_fine_20.pth"))),
             "was written by --plugin reflow [full_flow], but this run is the 4DGS baseline"),
        Case("poses_bounds.npy holding text",
             lambda s, w: ((s / "poses_bounds.npy").write_text("0 0 1\n"), _train("-s", str(s), "-m", str(w / "out"),
                                                                                 *SHORT))[1],
             "poses_bounds.npy is not a .npy file"),
        Case("transposed motion mask", lambda s, w: (_transpose_first_mask(s), _train("-s", str(s), "-m", str(w / "out"),
                                                                                      *SHORT))[1],
             "not a scaled copy"),
        Case("-r 100000", lambda s, w: _train("-s", str(s), "-m", str(w / "out"), *SHORT, "-r", "100000"),
             "GiB to hold them"),
        Case("-r 3", lambda s, w: _train("-s", str(s), "-m", str(w / "out"), *SHORT, "-r", "3"),
             "views need at least 4 px a side"),
        Case("one frame with --plugin reflow", lambda s, w: (_one_frame(s), _train(
            "-s", str(s), "-m", str(w / "out"), *SHORT[:-1], "--plugin", "reflow"))[1],
             "--plugin reflow needs at least 2 training frames for full_flow, cam_flow, comp_init"),
        Case("disk full at the first save", lambda s, w: _train("-s", str(s), "-m", str(w / "out"), *SHORT),
             "File too large", limit_file_size=60_000, untouched=False),
        Case("render an iteration the run did not save", lambda s, w: (_fake_finished_run(w / "out"),
                                                                      [str(ROOT / "render.py"), "-m", str(w / "out")])[1],
             "iteration_7 was not saved by the run"),
        Case("prepare: a text file as the video", lambda s, w: ((w / "clip.mp4").write_text("not a video"), [
            "-m", "baselines.prepare", str(w / "clip.mp4"), "-o", str(w / "out")])[1], "clip.mp4"),
        Case("evaluate: no such model folder", lambda s, w: ["-m", "reflow_plugin.evaluate", "-m", str(w / "out")],
             "out"),
        Case("ablate: train.py flags before --", lambda s, w: ["-m", "reflow_plugin.ablate", "-s", str(s), "-o",
                                                              str(w / "out"), "--iterations", "10"],
             "train.py flags go after '--'"),
        Case("report: no finished run", lambda s, w: ((w / "out").mkdir(), ["-m", "reflow_plugin.report",
                                                                          str(w / "out")])[1],
             "no finished run"),
        # issue 41
        Case("-m locked by another process", lambda s, w: _train("-s", str(s), "-m", str(_locked(w / "out")), *SHORT),
             "another process (pid"),
        Case('-m "" (an unset shell variable)', lambda s, w: _train("-s", str(s), "-m", "", *SHORT), "-m is empty"),
        Case("--no-eval checkpoint resumed with --eval", lambda s, w: _train(
            "-s", str(s), "-m", str(w / "out"), *SHORT[:-1], "--eval", "--start_checkpoint",
            str(_trained(s, w) / "chkpnt_fine_1.pth")), "it was trained with --no-eval: give the same"),
        Case("render: run.json truncated, a leftover iteration", lambda s, w: [
            str(ROOT / "render.py"), "-m", str(_garbage_run_json(s, w))], "run.json cannot be read",
             output="first"),
        Case("render: iteration folder without extra_buffers.pth", lambda s, w: [
            str(ROOT / "render.py"), "-m", str(_without_extra_buffers(s, w))], "extra_buffers.pth missing",
             output="first"),
        Case("render on a full disk", lambda s, w: [str(ROOT / "render.py"), "-m", str(_log_near_limit(s, w, 20_000))],
             "first/train_log.jsonl", output="first", limit_file_size=20_000, untouched=False, extra={"render": True}),
        Case("ablate --rows ''", lambda s, w: ["-m", "reflow_plugin.ablate", "-s", str(s), "-o", str(w / "out"),
                                              "--rows", ""], "--rows names none of"),
    ]


CASES = _case_list()


def _tree(folder: Path) -> dict[str, tuple] | None:
    """{relative path: (mtime_ns, sha1 of the bytes)}: no changed byte, no touched file."""
    if not folder.exists():
        return None
    if folder.is_file():
        return {"": _stamp(folder)}
    return {str(p.relative_to(folder)): _stamp(p) for p in folder.rglob("*")}


def _stamp(path: Path) -> tuple:
    return path.stat().st_mtime_ns, hashlib.sha1(path.read_bytes()).hexdigest() if path.is_file() else None


def _run_case(case: Case, scene: Path, work: Path) -> dict:
    local = work / "scene"
    shutil.copytree(scene, local)
    argv = case.make(local, work)
    before = _tree(work / case.output)

    def limit() -> None:
        if case.limit_file_size:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (case.limit_file_size, case.limit_file_size))

    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    env.pop("FOURDGS_TRACEBACK", None)
    start = time.perf_counter()
    cwd = case.extra["cwd"](work) if "cwd" in case.extra else ROOT
    done = subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True,
                          preexec_fn=limit, timeout=300)
    output = done.stdout + done.stderr
    return {"name": case.name, "rc": done.returncode, "output": output, "seconds": time.perf_counter() - start,
            "before": before, "after": _tree(work / case.output), "case": case, "work": work}


@pytest.fixture(scope="module")
def outcomes(tiny_scene, tmp_path_factory) -> dict[str, dict]:
    root = tmp_path_factory.mktemp("bad_inputs")
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = [pool.submit(_run_case, case, tiny_scene, root / f"case{i}") for i, case in enumerate(CASES)]
        results = [f.result() for f in futures]
    return {r["name"]: r for r in results}


@pytest.mark.parametrize("name", [c.name for c in CASES])
def test_bad_input_gives_one_error_line(outcomes, name):
    result = outcomes[name]
    case: Case = result["case"]
    output = result["output"]
    errors = [line for line in output.splitlines() if "error:" in line]
    assert result["rc"] == 2, output[-2000:]
    assert "Traceback" not in output, output[-2000:]
    assert len(errors) == 1 and case.expect in errors[0], output[-2000:]
    if case.untouched:
        assert result["after"] == result["before"], "the output folder changed"
    elif case.extra.get("render"):  # render.py may have written renders; its log lines are whole
        out = result["work"] / case.output
        assert all(json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines())
        assert json.loads((out / "run.json").read_text())["state"] == "finished"
    else:  # the failed run's record may stay; a half-written iteration folder may not
        out = result["work"] / case.output
        assert not list((out / "point_cloud").glob("*iteration_*")), sorted(p.name for p in (out / "point_cloud").iterdir())
        assert json.loads((out / "run.json").read_text())["state"] == "failed"


@pytest.mark.parametrize("signum,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_prints_one_line_with_the_resume_command(tiny_scene, tmp_path, signum, code):
    out = tmp_path / "out"
    argv = [sys.executable, str(ROOT / "train.py"), "-s", str(tiny_scene), "-m", str(out), "--configs", CONFIG,
            "--coarse_iterations", "100000", "--iterations", "1", "--quiet", "--no-eval", "--log_every", "1"]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    process = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = out / "train_log.jsonl"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and process.poll() is None:
        if log.is_file() and '"kind": "iter"' in log.read_text():
            break
        time.sleep(0.2)
    process.send_signal(signum)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == code, stderr[-2000:]
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.startswith("interrupted")]
    assert len(lines) == 1 and "last checkpoint" in lines[0] and "--start_checkpoint" in lines[0], stderr[-2000:]
    checkpoint = lines[0].split("last checkpoint ", 1)[1].split(";", 1)[0]
    assert Path(checkpoint).is_file() and json.loads((out / "run.json").read_text())["state"] == "interrupted"


def test_two_trainings_started_together_on_one_folder(tiny_scene, tmp_path):
    """Exactly one trains into the folder; the other ends with one line (the lock, or the finished run
    it finds), whichever order the OS runs them in."""
    out = tmp_path / "out"
    argv = _train("-s", str(tiny_scene), "-m", str(out), *SHORT, "--log_every", "1")
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    processes = [subprocess.Popen([sys.executable, *argv], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=300), p.communicate()[1], p.pid) for p in processes]
    codes = sorted(code for code, _, _ in results)
    assert codes == [0, 2], results
    winner = next(pid for code, _, pid in results if code == 0)
    loser = next(err for code, err, _ in results if code == 2)
    errors = [line for line in loser.splitlines() if "error:" in line]
    assert len(errors) == 1 and ("another process" in errors[0] or "already holds" in errors[0]), loser[-2000:]
    assert "Traceback" not in loser
    record = json.loads((out / "run.json").read_text())
    assert record["state"] == "finished" and record["pid"] == winner
    log = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    assert [r["kind"] for r in log].count("train_end") == 1 and [r["kind"] for r in log].count("model_created") == 1
    assert not (out / ".run.lock").exists()
