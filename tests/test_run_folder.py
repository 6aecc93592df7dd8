"""Run folders (issue 25): nothing lost, nothing mixed, nothing silent.

1  a model folder holding a run is refused before any work (--overwrite clears it, --start_checkpoint
   continues it); render.py renders only iterations the folder's run saved;
2  resuming a checkpoint under other plugins/components is an error naming both sides;
3  a failed save is one line (path + OS reason) and leaves no half-written iteration folder;
9  Ctrl-C stops at a consistent iteration with a checkpoint and the command that resumes it.
"""
from __future__ import annotations

import errno
import json
import logging
import os
import shlex
import shutil
from pathlib import Path

import pytest
import torch

from baselines.fourdgs.app import interrupted_line, render_from_argv, train_from_argv
from baselines.fourdgs.checkpoint import SaveError, save_point_cloud_dir
from baselines.run_folder import RunFolderError, TrainingInterrupted, read_run_record
from baselines.fourdgs.trainer import Trainer
from tests.test_trainer import base_argv, toy_plugin  # noqa: F401  (fixture)

FAST_RUN = ("--checkpoint_iterations", "3", "--no-eval")  # no test views: no evaluation renders


def _tree(folder: Path) -> dict[str, int]:
    """{relative path: mtime_ns} of everything in `folder` (to prove a refusal touched nothing)."""
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


def _train(scene, out, *extra, coarse=3, fine=3):
    return train_from_argv(base_argv(scene, out, coarse, fine, *FAST_RUN, *extra))


def test_a_folder_holding_a_run_is_refused_before_any_work(tiny_scene, tmp_path, toy_plugin, caplog):  # noqa: F811
    run = tmp_path / "run"
    _train(tiny_scene, run)
    assert read_run_record(run)["state"] == "finished"
    before = _tree(run)
    for extra in ((), ("--plugin", "toy_pairs"), ("--iterations", "5")):
        with pytest.raises(RunFolderError, match=r"already holds a finished run of the 4DGS baseline.*--overwrite"
                                                 r".*--start_checkpoint .*chkpnt_fine_3\.pth to continue"):
            _train(tiny_scene, run, *extra)
    assert _tree(run) == before

    (run / "notes.txt").write_text("mine")  # not a run's file: --overwrite keeps it
    shutil.copytree(run / "point_cloud" / "iteration_3", run / "point_cloud" / "iteration_3_backup")
    _train(tiny_scene, run, "--overwrite", fine=4)
    record = read_run_record(run)
    assert record["state"] == "finished" and record["saved"] == ["point_cloud/coarse_iteration_3",
                                                                 "point_cloud/iteration_4"]
    assert sorted(p.name for p in (run / "point_cloud").iterdir()) == ["coarse_iteration_3", "iteration_4"]
    assert (run / "notes.txt").read_text() == "mine"
    ends = [json.loads(line)["kind"] for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert ends.count("train_end") == 1  # one run's log, not two

    # a folder of an older run (no run.json) is refused too
    legacy = tmp_path / "legacy"
    shutil.copytree(run, legacy)
    (legacy / "run.json").unlink()
    with pytest.raises(RunFolderError, match="already holds an earlier run"):
        _train(tiny_scene, legacy)

    # render.py never renders (nor writes metrics of) an iteration the folder's run did not save
    shutil.copytree(run / "point_cloud" / "iteration_4", run / "point_cloud" / "iteration_99")
    with pytest.raises(RunFolderError, match="iteration_99 was not saved by the run"):
        render_from_argv(["-m", str(run), "--skip_video"])
    with caplog.at_level(logging.INFO):
        written = render_from_argv(["-m", str(run), "--iteration", "4", "--skip_video"])
    assert written["train"].name == "ours_4"
    assert any(r.levelno == logging.INFO for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.INFO):  # render.py's own --quiet, whatever the training run saved
        render_from_argv(["-m", str(run), "--iteration", "4", "--skip_video", "--quiet"])
        assert logging.getLogger().level == logging.INFO  # the caller's level is restored
    assert not [r.getMessage() for r in caplog.records if r.levelno < logging.WARNING]


def test_resume_must_match_the_checkpoints_plugins(tiny_scene, tmp_path, toy_plugin):  # noqa: F811
    toy, base = tmp_path / "toy", tmp_path / "base"
    _train(tiny_scene, toy, "--plugin", "toy_pairs")
    _train(tiny_scene, base)
    chk = str(toy / "chkpnt_fine_3.pth")
    with pytest.raises(RunFolderError, match=r"written by --plugin toy_pairs \[.*\], but this run is the 4DGS "
                                             r"baseline \(no plugin\)"):
        _train(tiny_scene, tmp_path / "b1", "--start_checkpoint", chk, fine=5)
    assert not (tmp_path / "b1").exists()  # the refused run left nothing behind
    with pytest.raises(RunFolderError, match=r"this run is --plugin toy_pairs.*give its point_cloud/iteration_N folder"):
        _train(tiny_scene, tmp_path / "b2", "--start_checkpoint", str(base / "chkpnt_fine_3.pth"),
               "--plugin", "toy_pairs", fine=5)
    with pytest.raises(RunFolderError, match=r"trained with --plugin toy_pairs, which this run lacks"):
        _train(tiny_scene, tmp_path / "b3", "--start_checkpoint", str(toy / "point_cloud" / "iteration_3"), fine=5)
    with pytest.raises(RunFolderError, match=r"holds a run of --plugin toy_pairs.*continues it as the 4DGS baseline"):
        _train(tiny_scene, toy, "--start_checkpoint", chk, fine=5)

    # continuing the same run in its own folder: allowed, recorded; a killed save's leftover goes
    stale = toy / "point_cloud" / ".iteration_4.tmp-killed"
    stale.mkdir()
    (stale / "point_cloud.ply").write_bytes(b"ply\n")
    _train(tiny_scene, toy, "--plugin", "toy_pairs", "--start_checkpoint", chk, fine=5)
    assert not stale.exists()
    record = read_run_record(toy)
    assert record["state"] == "finished" and "point_cloud/iteration_5" in record["saved"]
    assert "point_cloud/iteration_3" in record["saved"] and len(record["continued"]) == 1
    # an older run's folder (no run.json) continued: its iteration folders count as this run's
    (toy / "run.json").unlink()
    _train(tiny_scene, toy, "--plugin", "toy_pairs", "--start_checkpoint", str(toy / "chkpnt_fine_3.pth"), fine=6)
    assert {"point_cloud/iteration_3", "point_cloud/iteration_5", "point_cloud/iteration_6"} <= set(
        read_run_record(toy)["saved"])
    render_from_argv(["-m", str(toy), "--iteration", "5", "--skip_video", "--skip_train"])


def _failing_torch_save(name: str, monkeypatch) -> None:
    """torch.save fails on files called `name` as it does on a full disk (a RuntimeError whose context
    is the OSError of the failed write), after writing part of the file."""
    real_save = torch.save

    def save(obj, f, *args, **kwargs):
        if Path(getattr(f, "name", "")).name.startswith(f".{name}."):
            f.write(b"\0" * 64)
            try:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            except OSError:
                raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64 vs 0") from None
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)


def test_a_failed_save_is_one_line_and_leaves_no_torn_folder(tiny_scene, tmp_path, monkeypatch):
    run = tmp_path / "run"
    _failing_torch_save("deformation.pth", monkeypatch)
    with pytest.raises(SaveError) as caught:
        _train(tiny_scene, run)
    message = str(caught.value)
    assert message == (f"cannot write {run / 'point_cloud' / 'coarse_iteration_3' / 'deformation.pth'}: "
                       "[Errno 28] No space left on device")
    assert not (run / "point_cloud" / "coarse_iteration_3").exists()  # the PLY went with its folder
    assert list((run / "point_cloud").iterdir()) == []  # no temporary folder left either
    record = read_run_record(run)
    assert record["state"] == "failed" and "No space left" in record["reason"]


def test_an_existing_iteration_folder_is_replaced_whole(tiny_scene, tmp_path, monkeypatch):
    run = tmp_path / "run"
    summary = _train(tiny_scene, run)
    folder = run / "point_cloud" / "iteration_3"
    (folder / "stale.txt").write_text("from before")
    model = summary.trainer.ctx.model
    save_point_cloud_dir(model, folder)  # the same iteration again
    assert folder.is_dir() and not (folder / "stale.txt").exists()
    _failing_torch_save("deformation_table.pth", monkeypatch)
    (folder / "stale.txt").write_text("from before")
    with pytest.raises(SaveError, match="iteration_3/deformation_table.pth: .*No space left"):
        save_point_cloud_dir(model, folder)
    assert (folder / "stale.txt").is_file()  # a failed save leaves the old folder as it was
    assert sorted(p.name for p in (run / "point_cloud").iterdir()) == ["coarse_iteration_3", "iteration_3"]


def test_ctrl_c_stops_with_a_checkpoint_and_the_resume_command(tiny_scene, tmp_path, monkeypatch):
    run = tmp_path / "run"
    step = Trainer.train_step

    def step_then_press_ctrl_c(self):
        step(self)
        if self.ctx.stage == "coarse" and self.ctx.iteration == 2:
            self._stop.request()  # what the first SIGINT does

    monkeypatch.setattr(Trainer, "train_step", step_then_press_ctrl_c)
    argv = base_argv(tiny_scene, run, 3, 3, "--no-eval")
    with pytest.raises(TrainingInterrupted) as caught:
        train_from_argv(argv)
    checkpoint = run / "chkpnt_coarse_2.pth"
    assert caught.value.checkpoint == checkpoint and checkpoint.is_file()
    record = read_run_record(run)
    assert record["state"] == "interrupted" and record["stopped_at"] == "coarse iteration 2"
    line = interrupted_line(caught.value)
    assert "\n" not in line and line.startswith("interrupted at coarse iteration 2; last checkpoint ")
    command = line.split("; resume: ", 1)[1]
    assert command == record["resume"] and f"--start_checkpoint {checkpoint}" in command

    monkeypatch.setattr(Trainer, "train_step", step)
    train_from_argv(shlex.split(command)[2:])  # the printed command, as typed after "python train.py"
    record = read_run_record(run)
    assert record["state"] == "finished" and "point_cloud/iteration_3" in record["saved"]


def test_implicit_output_folder_is_never_reused_and_a_killed_run_is_named(tmp_path):
    from baselines.run_folder import RunIdentity, check_run_folder, default_model_path

    base = tmp_path / "output" / "scene"
    assert default_model_path(base) == base  # free: used as is
    base.mkdir(parents=True)
    record = {"format": "reflow-4dgs/run", "version": 1, "state": "running", "pid": 2**22 + 12345, "host": "x",
              "plugins": ["reflow"], "components": {"reflow": ["full_flow"]}, "stopped_at": "saved fine iteration 500"}
    (base / "run.json").write_text(json.dumps(record))
    (base / "chkpnt_fine_500.pth").write_bytes(b"")
    assert default_model_path(base) == tmp_path / "output" / "scene-2"
    with pytest.raises(RunFolderError, match=r"an unfinished run of --plugin reflow \[full_flow\] \(running, saved fine "
                                             r"iteration 500\).*--start_checkpoint .*chkpnt_fine_500.pth to continue"):
        check_run_folder(base, RunIdentity.of([], {}))


def test_folder_removed_by_a_racing_run_between_checks_is_a_free_folder(tmp_path, monkeypatch):
    """A second run started at the same moment removes the empty folder it probed between our
    is_dir() and the listing of the folder: that folder holds no run (was: an OSError line)."""
    from baselines import run_folder
    from baselines.run_folder import RunIdentity, check_run_folder

    folder = tmp_path / "out"
    folder.mkdir()
    real_read = run_folder.read_run_record

    def read_then_vanish(path):
        record = real_read(path)
        folder.rmdir()  # the other run's probe cleans up here
        return record

    monkeypatch.setattr(run_folder, "read_run_record", read_then_vanish)
    plan = check_run_folder(folder, RunIdentity.of([], {}))
    assert plan.path == folder and not plan.clear and not plan.continuing


def test_lock_survives_another_run_removing_the_folder_mid_mkdir(tmp_path, monkeypatch):
    """Path.mkdir's FileExistsError when the folder vanished between its mkdir and its is_dir() check
    (another run released the empty folder it had created) is a race, not an error; a FILE is one."""
    from baselines.run_folder import RunLock

    folder = tmp_path / "run"
    real_mkdir, raced = Path.mkdir, []

    def racing_mkdir(self, *args, **kwargs):
        if self == folder and not raced:  # the other run's folder existed at os.mkdir, gone at is_dir()
            raced.append(True)
            raise FileExistsError(errno.EEXIST, "File exists", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", racing_mkdir)
    lock = RunLock(folder).acquire()
    assert raced and lock.held and (folder / ".run.lock").exists()
    lock.release()
    monkeypatch.setattr(Path, "mkdir", real_mkdir)
    (tmp_path / "file").write_text("x")
    with pytest.raises(RunFolderError, match="cannot create it"):
        RunLock(tmp_path / "file").acquire()


def test_write_probe_of_a_folder_another_run_creates_or_removes_at_the_same_moment(tmp_path, monkeypatch):
    """The writability probe of a missing folder: another run creating it between our exists() and
    mkdir() (FileExistsError) leaves it to that run; that run removing the folder it probed just
    before our probe file (FileNotFoundError) is probed again; neither is "cannot create"."""
    import tempfile as tempfile_module

    from baselines.run_folder import _writable_error

    folder = tmp_path / "out"
    real_mkdir, real_mkstemp = Path.mkdir, tempfile_module.mkstemp

    def other_run_made_it(self, *args, **kwargs):
        if self == folder:
            real_mkdir(self)  # the other process wins the race
            raise FileExistsError(errno.EEXIST, "File exists", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", other_run_made_it)
    assert _writable_error(folder) is None
    assert folder.is_dir()  # not ours: not removed by the probe's clean-up
    monkeypatch.setattr(Path, "mkdir", real_mkdir)
    folder.rmdir()
    removed = []

    def other_run_removed_it(*args, **kwargs):
        if not removed:
            removed.append(True)
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(folder / ".write_probe.x"))
        return real_mkstemp(*args, **kwargs)

    monkeypatch.setattr(tempfile_module, "mkstemp", other_run_removed_it)
    assert _writable_error(folder) is None and removed
    assert not folder.exists()  # our own probe folder is cleaned up
    (tmp_path / "file").write_text("x")
    assert "is a file" in _writable_error(tmp_path / "file" / "sub")
