"""A run folder's identity: which run `-m` holds, recorded once and checked before any work.

    <model_path>/run.json   {"format", "version", "run_id", "state", "plugins", "components",
                             "source_path", "command", "pid", "host", "started", "updated",
                             "saved": [relative paths of point_cloud/(coarse_)iteration_N],
                             "checkpoints": [chkpnt files], "stopped_at", "reason", "foreign"}

Rules (`check_run_folder`, read-only, raises `RunFolderError` before anything is loaded):

- `-m` naming a file, or a folder that cannot be written (read-only, immutable, no permission),
  is refused.
- A folder that holds a run (run.json, or an older run's config.json / cfg_args / point_cloud /
  chkpnt files) is refused, with what it holds and the ways out: a new `-m`, `--overwrite`
  (clears the earlier run's files first, keeping files no run writes), or `--start_checkpoint`
  of that folder (continues it: plugins and components must match).
- When neither `-m` nor `--expname` is typed, the default `output/<scene>` is never reused: the
  run goes to the first free `output/<scene>-2`, `-3`, ... (logged).

`RunFolder.commit` then writes run.json (state "running"); the trainer records each saved
iteration folder and checkpoint, and the run ends "finished", "failed" (with the reason) or
"interrupted" (with the iteration and the last checkpoint). `render.py` renders only iteration
folders that the run described by the folder's config saved (`check_saved_iteration`).

One process at a time: `RunLock` holds an exclusive OS lock (``fcntl.flock``) on
``<model_path>/.run.lock`` from before the folder's first write to the end of the process's work
on it (train.py for the whole run, render.py while it writes), with the holder's PID written in the
file. A second process on the same folder is refused with one line naming that PID. A lock file
left behind by a killed process is not a lock: the OS drops a flock when its holder dies, so the
next run takes it at once (the PID in the file is only reported, never trusted). Where fcntl does
not exist (Windows) the lock is skipped, so the import still works.

This module imports no torch: train.py runs `precheck_model_folder` on a typed `-m` before torch
loads, so a refused folder costs no start-up time.
"""
from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

try:
    import fcntl
except ImportError:  # Windows: no flock; runs are not locked there
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger("train")

RUN_FILE = "run.json"
LOCK_FILE = ".run.lock"
RUN_FORMAT = "reflow-4dgs/run"
# what the host writes into a model folder (plugins add their own: Plugin.outputs)
HOST_OUTPUTS = ("run.json", "cfg_args", "config.json", "point_cloud", "test", "train", "video",
                "results.json", "per_view.json", "train_log.jsonl")
CHECKPOINT_PATTERN = re.compile(r"chkpnt_(coarse|fine)_(\d+)\.pth")
LEGACY_MARKERS = ("config.json", "cfg_args", "point_cloud")
RESTORED_FILES = ("run.json", "config.json", "cfg_args")  # put back when a continued run fails at start

_current: "RunFolder | None" = None  # the run of this process (for the interrupt message)
_held_locks: "dict[str, RunLock]" = {}  # real path of the folder -> this process's lock on it


class RunFolderError(ValueError):
    """A model folder that cannot take this run (one line: what is there, the ways out)."""


class TrainingInterrupted(Exception):
    """Training stopped on request (Ctrl-C, SIGTERM: `signum`) at a consistent point; `checkpoint`
    resumes it exactly."""

    def __init__(self, stage: str, iteration: int, checkpoint: Path | None, signum: int = 2) -> None:
        super().__init__(f"interrupted at {stage} iteration {iteration}")
        self.stage, self.iteration, self.checkpoint, self.signum = stage, iteration, checkpoint, signum


@dataclass(frozen=True)
class RunIdentity:
    """What makes two runs the same run: plugins, their active components and the dataset."""

    plugins: tuple[str, ...]
    components: dict[str, tuple[str, ...]]
    source_path: str = ""

    @classmethod
    def of(cls, plugins: Iterable[str], components: dict[str, Iterable[str]], source_path: str = "") -> "RunIdentity":
        return cls(tuple(plugins), {k: tuple(sorted(v)) for k, v in components.items()}, str(source_path))

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> "RunIdentity":
        return cls.of(record.get("plugins") or [], record.get("components") or {}, record.get("source_path") or "")

    def describe(self) -> str:
        if not self.plugins:
            return "the 4DGS baseline (no plugin)"
        parts = [f"--plugin {name}" + (f" [{', '.join(self.components[name]) or 'no component'}]"
                                       if name in self.components else "") for name in self.plugins]
        return " + ".join(parts)

    def same_method(self, other: "RunIdentity") -> bool:
        return self.plugins == other.plugins and self.components == other.components


def read_run_record(model_path: str | os.PathLike) -> dict[str, Any] | None:
    """The folder's run.json, or None (absent or unreadable: an older run, or no run)."""
    path = Path(model_path) / RUN_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format") == RUN_FORMAT else None


def require_run_record(model_path: str | os.PathLike) -> dict[str, Any] | None:
    """The folder's run.json; None only when there is none (an older or 4DGS output).

    A run.json that exists but cannot be read (truncated, garbage, another format) raises
    `RunFolderError`: without it nobody can tell which iteration folders the run saved, so no
    consumer may pick a "latest" one (it could be another run's leftover).
    """
    path = Path(model_path) / RUN_FILE
    if not path.exists():
        return None
    record = read_run_record(model_path)
    if record is None:
        raise RunFolderError(f"{path} cannot be read as this project's run record (truncated or overwritten?): "
                             "it says which iteration folders the run saved; restore it, or retrain with "
                             "--overwrite")
    return record


class RunLock:
    """An exclusive lock on a run folder, held by this process (see the module docstring).

    ``acquire()`` creates the folder if needed (``created`` says so) and the lock file, takes a
    non-blocking ``flock`` and writes this PID into it; a folder locked by another live process
    raises `RunFolderError`. ``release()`` removes the lock file (and the folder, if this lock
    created it and it stayed empty) and drops the lock; the OS drops it too if the process dies.
    A second lock on the same folder from the same process (a library user building one trainer
    after another) takes the lock over from the first: runs of one process follow each other.
    """

    def __init__(self, folder: str | os.PathLike, purpose: str = "using it (training or rendering)") -> None:
        self.folder, self.purpose = Path(folder), purpose
        self.path = self.folder / LOCK_FILE
        self.fd: int | None = None
        self.created = False

    @property
    def held(self) -> bool:
        return self.fd is not None

    def acquire(self) -> "RunLock":
        if self.fd is not None:
            return self
        key = os.path.realpath(self.folder)
        previous = _held_locks.pop(key, None)
        if previous is not None and previous.fd is not None:  # this process again: take the lock over
            self.created, previous.created = previous.created, False
            previous.release()
        else:
            self.created = not self.folder.exists()
        try:
            _make_folder(self.folder)
        except OSError as err:
            raise RunFolderError(f"-m {self.folder}: cannot create it ({err.strerror or err})") from None
        if fcntl is None:
            self.fd = -1
            _held_locks[key] = self
            return self
        races = 0
        while True:  # the holder removes the file on release: lock a file that is still the path's
            try:
                _make_folder(self.folder)  # a failed holder may have removed it
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except FileNotFoundError:  # the folder went between the two calls: another run released it
                races += 1
                if races < 20:
                    continue
                raise RunFolderError(f"cannot create {self.path}: its folder keeps disappearing") from None
            except OSError as err:
                self._undo_folder()
                raise RunFolderError(f"cannot create {self.path} ({err.strerror or err})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = _read_pid(fd)
                os.close(fd)
                raise RunFolderError(f"-m {self.folder}: another process (pid {holder or 'unknown'}) is "
                                     f"{self.purpose}; wait for it to end, or choose another -m") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self.fd = fd
        _held_locks[key] = self
        return self

    def release(self) -> None:
        """Drop the lock (idempotent); the lock file goes first, so no one locks a removed file."""
        if self.fd is None:
            return
        fd, self.fd = self.fd, None
        key = os.path.realpath(self.folder)
        if _held_locks.get(key) is self:
            del _held_locks[key]
        if fd >= 0:
            try:
                os.unlink(self.path)
            except OSError:  # already gone: a lock file is no lock once its flock is dropped
                pass
            os.close(fd)
        self._undo_folder()

    def _undo_folder(self) -> None:
        if self.created:
            try:
                self.folder.rmdir()  # only if this run wrote nothing else into it
            except OSError:  # not empty (or gone): the folder stays as it is
                pass


def _make_folder(folder: Path, attempts: int = 20) -> None:
    """`folder.mkdir(parents=True, exist_ok=True)` that survives another process removing the folder.

    Path.mkdir raises FileExistsError when its mkdir finds the folder but the folder is gone by its
    is_dir() check: another run's lock released an empty folder it had created (`_undo_folder`)
    in between. That is no error: the next attempt creates it. A FILE at the path still raises.
    """
    for _ in range(attempts - 1):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            return
        except FileExistsError:
            if folder.exists() and not folder.is_dir():  # a file, not a race
                raise
    folder.mkdir(parents=True, exist_ok=True)


def _read_pid(fd: int) -> int | None:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 32).decode(errors="replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None


def _holds_run(folder: Path) -> bool:
    """Whether `folder` holds a run's files; False once it is gone.

    A second run started at the same moment may remove the empty folder it probed or created
    (`_writable_error`, `RunLock._undo_folder`) between our is_dir() and iterdir(): a folder that
    vanished holds no run, and the lock taken next settles which of the two trains.
    """
    if (folder / RUN_FILE).exists() or any((folder / m).exists() for m in LEGACY_MARKERS):
        return True
    try:
        return any(CHECKPOINT_PATTERN.fullmatch(p.name) for p in folder.iterdir())
    except FileNotFoundError:
        return False


def _writable_error(folder: Path, attempts_left: int = 2) -> str | None:
    """Why `folder` (existing, or to be created) cannot be written, or None.

    Two runs started at the same moment probe the same missing folder: a folder the other one
    created is used (and left to it), and one it removed again is probed anew (`attempts_left`).

    Really tries (access() says yes to root on a read-only or immutable folder): creates the
    missing folders and a probe file, then removes all of them again.
    """
    missing = []
    existing = folder
    while not existing.exists() and existing.parent != existing:
        missing.append(existing)
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        return f"{existing} is a file, not a folder"
    created: list[Path] = []
    try:
        for path in reversed(missing):
            try:
                path.mkdir()
            except FileExistsError:
                if not path.is_dir():
                    raise
                continue  # another process (a second run started at the same moment) made it: not ours to remove
            created.append(path)
        fd, name = tempfile.mkstemp(dir=folder, prefix=".write_probe.")
        os.close(fd)
        os.unlink(name)
    except FileNotFoundError as err:
        if attempts_left > 0 and err.filename is not None:  # a racing probe removed a folder it had made
            return _writable_error(folder, attempts_left - 1)
        return f"cannot create {err.filename or folder} ({err.strerror or err})"
    except OSError as err:
        where = f"cannot create {err.filename or folder}" if len(created) < len(missing) else "cannot write into it"
        return f"{where} ({err.strerror or err})"
    finally:
        for path in reversed(created):
            try:
                path.rmdir()
            except OSError:
                pass
    return None


def _pid_alive(pid: Any, host: Any) -> bool:
    if not isinstance(pid, int) or host != socket.gethostname() or pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def last_checkpoint(model_path: Path, record: dict[str, Any] | None = None) -> Path | None:
    """The newest chkpnt_<stage>_<N>.pth of the folder (fine after coarse), or None."""
    found = []
    for p in model_path.glob("chkpnt_*.pth"):
        m = CHECKPOINT_PATTERN.fullmatch(p.name)
        if m:
            found.append(((m.group(1) == "fine", int(m.group(2))), p))
    return max(found)[1] if found else None


def _describe_held(model_path: Path, record: dict[str, Any] | None) -> str:
    if record is None and (model_path / RUN_FILE).exists():
        return f"a run whose {RUN_FILE} cannot be read (truncated or overwritten?)"
    if record is None:
        from arguments.saved import read_saved_plugins

        try:
            plugins = read_saved_plugins(model_path)
        except Exception:  # an unreadable config of an older run: say what we know
            plugins = []
        what = f"--plugin {','.join(plugins)}" if plugins else "no plugin recorded"
        return f"an earlier run ({what})"
    identity = RunIdentity.from_record(record)
    state = record.get("state")
    if state == "running" and _pid_alive(record.get("pid"), record.get("host")):
        return f"a run of {identity.describe()} that is still training (pid {record.get('pid')})"
    if state == "finished":
        return f"a finished run of {identity.describe()}"
    stopped = record.get("stopped_at") or "before its first saved iteration"
    return f"an unfinished run of {identity.describe()} ({state or 'killed'}, {stopped})"


@dataclass
class FolderPlan:
    """What `check_run_folder` decided: where the run goes and what commit must do first."""

    path: Path
    existed: bool
    clear: bool = False  # --overwrite: the earlier run's files go first
    continuing: bool = False  # --start_checkpoint of this same folder
    previous: dict[str, Any] | None = None
    clear_names: list[str] = field(default_factory=list)


def default_model_path(base: Path) -> Path:
    """`base`, or the first of base-2, base-3, ... that holds no run (the implicit output folder)."""
    candidate, n = base, 1
    while candidate.is_dir() and _holds_run(candidate):
        n += 1
        candidate = base.with_name(f"{base.name}-{n}")
    if candidate != base:
        log.warning("%s holds an earlier run; this run writes to %s (-m to choose the folder)", base, candidate)
    return candidate


def check_run_folder(model_path: Path, identity: RunIdentity, *, overwrite: bool = False,
                     start_checkpoint: str | None = None, plugin_outputs: Iterable[str] = ()) -> FolderPlan:
    """Decide whether `model_path` may take this run; raise `RunFolderError` (nothing written) if not."""
    model_path = Path(model_path)
    if model_path.exists() and not model_path.is_dir():
        raise RunFolderError(f"-m {model_path}: is a file, not a folder; choose another -m")
    problem = _writable_error(model_path)
    if problem:
        raise RunFolderError(f"-m {model_path}: {problem}; choose another -m")
    if not model_path.is_dir():
        return FolderPlan(model_path, existed=False)
    record = read_run_record(model_path)
    if not _holds_run(model_path):
        return FolderPlan(model_path, existed=True)
    resume_dir = _checkpoint_folder(start_checkpoint)
    if resume_dir is not None and _same_path(resume_dir, model_path) and not overwrite:
        if record is not None:
            held = RunIdentity.from_record(record)
            if not held.same_method(identity):
                raise RunFolderError(
                    f"-m {model_path} holds a run of {held.describe()}; this command continues it as "
                    f"{identity.describe()}: give the same --plugin/--disable/--enable, or a new -m to start "
                    "a different run from that checkpoint")
            if record.get("state") == "running" and _pid_alive(record.get("pid"), record.get("host")):
                raise RunFolderError(f"-m {model_path}: another process (pid {record.get('pid')}) is training into it")
        return FolderPlan(model_path, existed=True, continuing=True, previous=record)
    if overwrite:
        if record is not None and record.get("state") == "running" and _pid_alive(record.get("pid"), record.get("host")):
            raise RunFolderError(f"-m {model_path}: another process (pid {record.get('pid')}) is training into it; "
                                 "--overwrite would pull its files away")
        return FolderPlan(model_path, existed=True, clear=True, previous=record,
                          clear_names=_run_entries(model_path, record, plugin_outputs))
    held = _describe_held(model_path, record)
    ways = [f"a new -m, --overwrite to clear it first"]
    checkpoint = last_checkpoint(model_path, record)
    if checkpoint is not None:
        ways.append(f"--start_checkpoint {checkpoint} to continue it")
    else:
        ways.append("--start_checkpoint <its chkpnt_*.pth> to continue it (it has none: "
                    "--checkpoint_iterations writes them)")
    raise RunFolderError(f"-m {model_path} already holds {held}; choose {', or '.join(ways)}")


def _checkpoint_folder(start_checkpoint: str | None) -> Path | None:
    """The model folder a --start_checkpoint belongs to (chkpnt file's folder, or OLD of OLD/point_cloud/...)."""
    if not start_checkpoint:
        return None
    path = Path(start_checkpoint).expanduser()
    if path.is_file():
        return path.parent
    if path.is_dir():
        if (path / "point_cloud.ply").is_file() and path.parent.name == "point_cloud":
            return path.parent.parent
        return path
    return None


def _same_path(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve()
    except OSError:
        return False


def _run_entries(model_path: Path, record: dict[str, Any] | None, plugin_outputs: Iterable[str]) -> list[str]:
    """Entries of the folder that a run wrote (host outputs, checkpoints, temporaries, plugins' outputs)."""
    known = set(HOST_OUTPUTS) | set(plugin_outputs)
    foreign = set((record or {}).get("foreign") or [])
    names = []
    for entry in model_path.iterdir():
        name = entry.name
        if name in foreign:
            continue
        if name in known or CHECKPOINT_PATTERN.fullmatch(name) or (name.startswith(".") and ".tmp" in name):
            names.append(name)
    return sorted(names)


class RunFolder:
    """The claimed model folder of a run: writes and updates run.json (atomically)."""

    def __init__(self, plan: FolderPlan, identity: RunIdentity, command: list[str]) -> None:
        self.plan, self.path, self.identity, self.command = plan, plan.path, identity, list(command)
        self.record: dict[str, Any] = {}
        self.created = False
        self.writes = 0  # iteration folders and checkpoints this process saved
        self.lock = RunLock(self.path)  # taken by `claim` before the folder's first write

    def claim(self, recheck: "Callable[[], FolderPlan]") -> None:
        """Lock the folder for this process, then decide again under the lock (`recheck`: the
        `check_run_folder` call that made the plan): a run that committed between the first check
        and the lock is seen now. Raises `RunFolderError` (lock released) if the folder is taken."""
        self.lock.acquire()
        try:
            self.plan = recheck()
        except BaseException:
            self.lock.release()
            raise

    def release(self) -> None:
        """End this process's hold on the folder (the OS would drop the lock at exit anyway)."""
        self.lock.release()

    def commit(self) -> None:
        """Clear (--overwrite), create the folder and write run.json: from here on the folder is this run's."""
        global _current
        plan = self.plan
        if plan.clear:
            for name in plan.clear_names:
                entry = self.path / name
                shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
            log.info("--overwrite: cleared %s of the earlier run (%s)", self.path, ", ".join(plan.clear_names) or "nothing")
        self.created = self.lock.created or not self.path.exists()
        self.path.mkdir(parents=True, exist_ok=True)
        stale = remove_stale_staging(self.path)
        if stale:
            log.info("removed %d half-written iteration folder(s) a killed run left: %s", len(stale),
                     ", ".join(p.name for p in stale))
        self._snapshot()
        previous = plan.previous if plan.continuing else None
        foreign = sorted(p.name for p in self.path.iterdir()
                         if p.name not in (RUN_FILE, LOCK_FILE)) if not plan.continuing else []
        now = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        self.record = {
            "format": RUN_FORMAT, "version": 1,
            "run_id": (previous or {}).get("run_id") or uuid.uuid4().hex,
            "state": "running", "plugins": list(self.identity.plugins),
            "components": {k: list(v) for k, v in self.identity.components.items()},
            "source_path": self.identity.source_path, "command": self.command,
            "pid": os.getpid(), "host": socket.gethostname(),
            "started": (previous or {}).get("started", now), "updated": now,
            "saved": list((previous or {}).get("saved", self._existing_iterations() if plan.continuing else [])),
            "checkpoints": list((previous or {}).get("checkpoints", [])),
            "foreign": list((previous or {}).get("foreign", foreign)),
        }
        if previous is not None:
            self.record["continued"] = list(previous.get("continued", [])) + [now]
        self._write()
        _current = self

    def _existing_iterations(self) -> list[str]:
        """Iteration folders of an older run (no run.json) this run continues: its own, so render.py may use them."""
        root = self.path / "point_cloud"
        return sorted(str(p.relative_to(self.path)) for p in root.iterdir()
                      if p.is_dir() and re.fullmatch(r"(coarse_)?iteration_\d+", p.name)) if root.is_dir() else []

    def _snapshot(self) -> None:
        """What the folder held before this run wrote anything (for `abandon`)."""
        self._before = {p.name for p in self.path.iterdir()}
        self._saved_bytes = {name: (self.path / name).read_bytes() for name in RESTORED_FILES
                             if (self.path / name).is_file()}
        log_file = self.path / "train_log.jsonl"
        self._log_size = log_file.stat().st_size if log_file.is_file() else None

    def abandon(self) -> None:
        """Undo this run's writes after a failure before its first iteration (a bad input found late):
        a folder it created is removed; otherwise new entries go and run.json / config.json /
        cfg_args / train_log.jsonl are put back as they were. Best effort."""
        global _current
        if _current is self:
            _current = None
        try:
            if self.created:
                self.lock.release()
                shutil.rmtree(self.path, ignore_errors=True)
                return
            for entry in self.path.iterdir():
                if entry.name not in self._before:
                    shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() else entry.unlink()
            for name, data in self._saved_bytes.items():
                (self.path / name).write_bytes(data)
            log_file = self.path / "train_log.jsonl"
            if self._log_size is not None and log_file.is_file():
                os.truncate(log_file, self._log_size)
        except OSError:
            pass
        finally:
            self.lock.release()

    def _write(self) -> None:
        from arguments.saved import atomic_write_text

        self.record["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        atomic_write_text(self.path / RUN_FILE, json.dumps(self.record, indent=1) + "\n")

    def record_saved(self, folder: Path, stage: str, iteration: int) -> None:
        rel = str(Path(folder).relative_to(self.path)) if Path(folder).is_relative_to(self.path) else str(folder)
        self.writes += 1
        if rel not in self.record["saved"]:
            self.record["saved"].append(rel)
        self.record["stopped_at"] = f"saved {stage} iteration {iteration}"
        self._write()

    def record_checkpoint(self, path: Path, stage: str, iteration: int) -> None:
        self.writes += 1
        name = Path(path).name
        if name not in self.record["checkpoints"]:
            self.record["checkpoints"].append(name)
        self.record["last_checkpoint"] = str(path)
        self._write()

    def record_facts(self, **facts: Any) -> None:
        """Add facts about the run to run.json (e.g. the machine it trains on), written at once."""
        self.record.update(facts)
        self._write()

    def end(self, state: str, reason: str | None = None, **facts: Any) -> None:
        """Mark the run finished / failed / interrupted (best effort: never masks the original error)."""
        global _current
        self.record.update(state=state, **facts)
        if reason:
            self.record["reason"] = reason
        try:
            self._write()
        except OSError:
            pass
        if state != "running" and _current is self:
            _current = None if state == "finished" else self


def remove_stale_staging(model_path: str | os.PathLike) -> list[Path]:
    """Delete the temporary iteration folders (`point_cloud/.iteration_N.tmp-*`, `.old-*`) that a
    killed save left; nothing reads them (checkpoint.save_point_cloud_dir writes them)."""
    root = Path(model_path) / "point_cloud"
    if not root.is_dir():
        return []
    stale = [p for p in root.glob(".*") if p.is_dir() and (".tmp-" in p.name or ".old-" in p.name)]
    for path in stale:
        shutil.rmtree(path, ignore_errors=True)
    return stale


def current_run() -> RunFolder | None:
    """The run folder this process claimed last (None before a run commits one)."""
    return _current


def check_saved_iteration(model_path: Path, folder: Path) -> None:
    """render.py's check: `folder` must have been saved by the run the model folder describes."""
    record = require_run_record(model_path)
    if record is None:
        return  # an older or 4DGS output: nothing recorded to check against
    rel = str(folder.relative_to(model_path)) if folder.is_relative_to(model_path) else str(folder)
    if rel not in record.get("saved", []):
        saved = ", ".join(record.get("saved", [])) or "none"
        raise RunFolderError(f"{folder} was not saved by the run {model_path}/{RUN_FILE} describes "
                             f"(its saved iterations: {saved}); it belongs to another run: render one of those, "
                             "or retrain with --overwrite")


def check_resume_identity(spec: str, extra: dict[str, Any] | None, mine: RunIdentity) -> None:
    """An exact resume (chkpnt file) continues the same method: the checkpoint's plugins and components."""
    extra = extra or {}
    recorded = extra.get("run")
    if recorded is not None:
        theirs = RunIdentity.of(recorded.get("plugins") or [], recorded.get("components") or {})
        same = theirs.same_method(mine)
    else:  # older checkpoints of ours name their plugins' states; 4DGS's have none
        theirs = RunIdentity.of(sorted((extra.get("plugins") or {}).keys()), {})
        same = sorted(theirs.plugins) == sorted(mine.plugins)
    if not same:
        upgrade = (" (to start a plugin run from a trained 4DGS model, give its point_cloud/iteration_N folder)"
                   if not theirs.plugins else "")
        raise RunFolderError(f"--start_checkpoint {spec} was written by {theirs.describe()}, but this run is "
                             f"{mine.describe()}: resume with the same --plugin/--disable/--enable{upgrade}")


def check_upgrade_plugins(path: Path, mine: RunIdentity) -> None:
    """Continuing from an output folder may add plugins (the upgrade path), never drop one."""
    from arguments.saved import model_dir_of_checkpoint, read_saved_plugins

    model_dir = model_dir_of_checkpoint(path) or path
    missing = [name for name in read_saved_plugins(model_dir) if name not in mine.plugins]
    if missing:
        raise RunFolderError(f"--start_checkpoint {path}: that run was trained with --plugin {','.join(missing)}, "
                             f"which this run lacks (it would train on as {mine.describe()}): "
                             f"add --plugin {','.join(missing)}")


def check_typed_model_path(value: str | None, flag: str = "-m") -> None:
    """An empty `-m ""` (an unset shell variable) is refused: it would mean the default folder."""
    if value is not None and not value.strip():
        raise RunFolderError(f'{flag} is empty ({flag} "", an unset shell variable?): give a folder, or leave '
                             f"{flag} out for the default")


def precheck_model_folder(argv: list[str]) -> None:
    """train.py's first check, before torch loads: a typed `-m` that is a file, cannot be written, or
    (without --overwrite / --start_checkpoint) holds a run. The full check follows the parse."""
    from baselines.cli_exit import flag_value, has_flag

    model = flag_value(argv, "-m", "--model_path")
    if has_flag(argv, "-h", "--help"):
        return
    check_typed_model_path(model)
    if not model:
        return
    if has_flag(argv, "--overwrite") or flag_value(argv, "--start_checkpoint"):
        problem = _writable_error(Path(model)) if not Path(model).is_file() else "is a file, not a folder"
        if problem:
            raise RunFolderError(f"-m {model}: {problem}; choose another -m")
        return
    check_run_folder(Path(model), RunIdentity.of([], {}))
