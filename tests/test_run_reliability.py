"""Run folders under stress (issue 41): nothing mixed, nothing stale, nothing torn.

1  a folder locked by another process is refused with one line naming its PID; a lock file left by a
   dead process is no lock; render.py takes the lock too;
2  runner paths (ablate, sweep) are the caller's, not the checkout's; `-m ""` is refused;
3  a resume checks the training cameras by name (another set, or another --eval, is refused; the same
   set in another order is re-mapped exactly);
4  an iteration folder missing a file its run saved, or holding another run's file, is refused;
5  an unreadable run.json stops render.py from picking a "latest" iteration;
6  prepare --masks refuses masks of another shape, as train.py does;
7  log lines are appended whole (a full disk undoes the partial line) and readers skip a torn tail.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from baselines.fourdgs import app
from baselines.fourdgs.app import render_from_argv, train_from_argv
from baselines.fourdgs.sampler import CameraSampler
from baselines.fourdgs import trainer
from baselines import run_folder
from baselines.run_folder import RunFolderError, read_run_record
from tests.test_trainer import base_argv

ROOT = Path(__file__).resolve().parents[1]
FAST_RUN = ("--checkpoint_iterations", "3", "--no-eval", "--save_iterations", "3")


def _tree(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


def _train(scene, out, *extra, coarse=2, fine=3):
    return train_from_argv(base_argv(scene, out, coarse, fine, *FAST_RUN, *extra))


@pytest.fixture(scope="module")
def finished(tiny_scene, tmp_path_factory) -> Path:
    """One finished 4DGS run (coarse 2 + fine 3, checkpoint at fine 3); tests copy it before changing it."""
    run = tmp_path_factory.mktemp("reliability") / "run"
    _train(tiny_scene, run)
    return run


def _copy(run: Path, tmp_path: Path, name: str = "copy") -> Path:
    target = tmp_path / name
    shutil.copytree(run, target)
    return target


class _Holder:
    """Another process holding the lock of `folder` until `release()` (it waits on its stdin)."""

    def __init__(self, folder: Path) -> None:
        code = ("import sys; from pathlib import Path; from baselines.run_folder import RunLock; "
                f"lock = RunLock(Path({str(folder)!r})).acquire(); print('held', flush=True); sys.stdin.read(); "
                "lock.release()")
        self.process = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, text=True)
        assert self.process.stdout.readline().strip() == "held"

    def release(self) -> None:
        self.process.communicate("", timeout=60)
        assert self.process.returncode == 0


def test_a_locked_folder_is_refused_and_a_stale_lock_file_is_not_a_lock(tiny_scene, finished, tmp_path):
    out = tmp_path / "out"
    holder = _Holder(out)
    try:
        before = _tree(out)
        pid = holder.process.pid
        with pytest.raises(RunFolderError, match=rf"-m {out}: another process \(pid {pid}\) is using it"):
            _train(tiny_scene, out)
        assert _tree(out) == before  # refused before the first write
        assert (out / run_folder.LOCK_FILE).read_text().strip() == str(pid)
    finally:
        holder.release()
    assert not out.exists()  # the lock created the folder and removed it again

    # a lock file a killed process left (no flock on it any more): the run takes the folder
    out.mkdir()
    (out / run_folder.LOCK_FILE).write_text("999999999\n")
    _train(tiny_scene, out)
    assert read_run_record(out)["state"] == "finished" and not (out / run_folder.LOCK_FILE).exists()

    # render.py writes into the folder too: it waits for no one, it refuses
    run = _copy(finished, tmp_path, "render_me")
    holder = _Holder(run)
    try:
        with pytest.raises(RunFolderError, match="another process"):
            render_from_argv(["-m", str(run), "--skip_video", "--skip_train"])
    finally:
        holder.release()
    # within one process, runs follow each other: a later claim takes the lock over
    first = run_folder.RunLock(run).acquire()
    second = run_folder.RunLock(run).acquire()
    assert first.fd is None and second.held and (run / run_folder.LOCK_FILE).is_file()
    second.release()
    assert not (run / run_folder.LOCK_FILE).exists() and run.is_dir()


def test_an_empty_model_path_is_refused(tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setattr(app, "REPO_ROOT", tmp_path)  # where an empty -m used to train (output/<scene>)
    argv = base_argv(tiny_scene, tmp_path / "x", 1, 1, *FAST_RUN)
    argv[argv.index("-m") + 1] = ""
    with pytest.raises(RunFolderError, match=r'-m is empty \(-m "", an unset shell variable\?\)'):
        train_from_argv(argv)
    assert not (tmp_path / "output").exists()


def test_runner_paths_are_the_callers(tmp_path, monkeypatch):
    from reflow_plugin.ablate import parse_runner_args, plan, resolve_scenes, ROWS

    (tmp_path / "scene").mkdir()
    (tmp_path / "extra.py").write_text("")
    monkeypatch.chdir(tmp_path)
    args, rows, extra = parse_runner_args(["-s", "scene", "-o", "abl", "--rows", "baseline", "--", "--configs",
                                           "extra.py", "--iterations", "10"], "ablate", "", "rows", ROWS)
    assert args.out == tmp_path / "abl" and extra == ["--configs", str(tmp_path / "extra.py"), "--iterations", "10"]
    spec, = plan(resolve_scenes(args.source), rows, args.out, extra)
    command = list(spec.command)
    assert command[command.index("-s") + 1] == str(tmp_path / "scene")
    assert command[command.index("-m") + 1] == str(tmp_path / "abl" / "scene" / "baseline")
    with pytest.raises(SystemExit):
        parse_runner_args(["-s", "scene", "-o", "abl", "--rows", ""], "ablate", "", "rows", ROWS)


def test_resume_checks_the_training_cameras_by_name(tiny_scene, finished, tmp_path):
    checkpoint = finished / "chkpnt_fine_3.pth"
    saved = torch.load(checkpoint, weights_only=False)["extra"]["cameras"]
    assert saved["eval"] is False and len(saved["train"]) == 12
    # --no-eval checkpoint resumed with --eval: 2 cameras fewer, named, and the flag to give
    argv = base_argv(tiny_scene, tmp_path / "r1", 2, 5, "--start_checkpoint", str(checkpoint), "--eval")
    with pytest.raises(ValueError, match=r"other training cameras \(12 training cameras in the checkpoint, 10 here; "
                                         r"not here: .*\); it was trained with --no-eval: give the same"):
        train_from_argv(argv)
    assert not (tmp_path / "r1").exists()
    # a dataset with fewer frames (no --eval difference): refused naming what is gone
    names = saved["train"]
    with pytest.raises(ValueError, match=rf"not here: {names[-1]}\); resume on the dataset it was trained on"):
        trainer.check_resume_cameras("x.pth", {"cameras": {"train": names, "eval": False}}, names[:-1], False)
    # an older checkpoint without names: its sampler's indices must exist
    with pytest.raises(ValueError, match="trained on at least 12 training cameras, this dataset gives 11"):
        trainer.check_resume_cameras("x.pth", {"sampler": {"stack": [11, 3]}}, names[:-1], False)


def test_the_same_cameras_in_another_order_resume_exactly():
    names = [f"cam{i}" for i in range(6)]
    first = CameraSampler(names, seed=3)
    first.next_batch(4)
    state = first.state_dict()
    expected = first.next_batch(9)

    shuffled = [names[i] for i in (4, 1, 5, 0, 3, 2)]
    order = trainer.check_resume_cameras("x.pth", {"cameras": {"train": names, "eval": False}}, shuffled, False)
    resumed = CameraSampler(shuffled, seed=99)
    resumed.items = [shuffled[i] for i in order]  # what Trainer._restore does
    resumed.load_state_dict(state)
    assert resumed.next_batch(9) == expected


def test_an_incomplete_or_altered_iteration_folder_is_refused(tiny_scene, finished, tmp_path):
    other = tmp_path / "other"
    _train(tiny_scene, other, "--seed", "7")
    run = _copy(finished, tmp_path)
    folder = run / "point_cloud" / "iteration_3"
    (folder / "extra_buffers.pth").unlink()
    with pytest.raises(ValueError, match=r"iteration_3 is incomplete: extra_buffers.pth missing"):
        render_from_argv(["-m", str(run), "--skip_video", "--skip_train"])
    assert not (run / "results.json").exists()
    shutil.copy(finished / "point_cloud" / "iteration_3" / "extra_buffers.pth", folder)
    shutil.copy(other / "point_cloud" / "iteration_3" / "deformation.pth", folder)  # same shapes, another run
    with pytest.raises(ValueError, match=r"iteration_3/deformation.pth is not the file the run saved there"):
        render_from_argv(["-m", str(run), "--skip_video", "--skip_train"])
    # the same check guards --start_checkpoint of a folder, without the "pass --configs" hint
    with pytest.raises(ValueError, match=r"deformation.pth is not the file the run saved there[^;]*$"):
        _train(tiny_scene, tmp_path / "up", "--start_checkpoint", str(folder), fine=4)


def test_an_unreadable_run_json_picks_no_latest_iteration(finished, tmp_path):
    run = _copy(finished, tmp_path)
    shutil.copytree(run / "point_cloud" / "iteration_3", run / "point_cloud" / "iteration_40")  # a leftover
    text = (run / "run.json").read_text()
    for broken in (text[: len(text) // 2], "garbage"):
        (run / "run.json").write_text(broken)
        with pytest.raises(RunFolderError, match=r"run.json cannot be read as this project's run record"):
            render_from_argv(["-m", str(run), "--skip_video", "--skip_train"])
        with pytest.raises(RunFolderError, match=r"run.json cannot be read"):
            app.require_run(run)
    assert not (run / "test").exists() and not (run / "results.json").exists()


@pytest.mark.parametrize("shape", [(96, 72), (10, 10)])  # numpy (rows, columns): transposed, square
def test_prepare_refuses_masks_of_another_shape(tmp_path, shape):
    import cv2

    from baselines.prepare.errors import PrepareError
    from baselines.prepare.masks import read_mask_folder

    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i:05d}.png"), np.full((72, 96), 255, np.uint8))
    assert len(read_mask_folder(tmp_path, 3, (48, 36))) == 3  # another resolution, same shape: fine
    cv2.imwrite(str(tmp_path / "00001.png"), np.full(shape, 255, np.uint8))
    with pytest.raises(PrepareError, match=rf"mask .*00001.png is {shape[1]}x{shape[0]} but its image is 48x36: "
                                           "not a scaled copy"):
        read_mask_folder(tmp_path, 3, (48, 36))


def test_log_lines_are_whole_after_a_full_disk(tmp_path):
    log = tmp_path / "train_log.jsonl"
    script = textwrap.dedent(f"""
        import resource, signal, sys
        from pathlib import Path
        sys.path.insert(0, {str(ROOT)!r})
        from baselines.fourdgs.run_log import RunLog
        run_log = RunLog(Path({str(log)!r}), quiet=True)
        run_log.event("first")
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (300, 300))
        try:
            for i in range(100):
                run_log.event("test", payload="x" * 70, i=i)
        except OSError as err:
            print(err)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert str(log) in done.stdout and "Errno 27" in done.stdout, done.stdout + done.stderr
    text = log.read_text()
    assert text.endswith("\n") and all(json.loads(line) for line in text.splitlines())


def test_report_skips_a_torn_last_log_line(finished, tmp_path, capsys, caplog):
    from reflow_plugin import report

    out = tmp_path / "sweep"
    run = _copy(finished, out / "scene", "row")
    (run / "results.json").write_text(json.dumps({"ours_3": {"PSNR": 20.0}}))
    with open(run / "train_log.jsonl", "a") as handle:
        handle.write('{"kind": "test", "iter')  # a write that did not finish
    assert report.main([str(out), "--plot", str(tmp_path / "plot.png")]) == 0
    assert "train_log.jsonl: last line" in caplog.text and "is cut off" in caplog.text
    capsys.readouterr()
    lines = (run / "train_log.jsonl").read_text().splitlines()
    (run / "train_log.jsonl").write_text("\n".join(lines[:2] + ["{torn"] + lines[2:]) + "\n")
    assert report.main([str(out), "--plot", str(tmp_path / "plot.png")]) == 2
    assert f"{run / 'train_log.jsonl'}: line 3 is not JSON" in capsys.readouterr().err
