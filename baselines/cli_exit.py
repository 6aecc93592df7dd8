"""How the command lines end: one line per failure, and the resume line after Ctrl-C.

    run_cli(main)      # train.py, render.py, python -m reflow_plugin.evaluate

- input errors (bad flags, files, config keys, plugins, model folders), OS failures (a full disk, a
  read-only folder: the path and the OS reason) and a diverged training print ``error: ...``
  (one line) and exit 2;
- Ctrl-C (or SIGTERM) prints where the run stopped, its last checkpoint and the exact command that
  resumes it, and exits 130 (143 after SIGTERM).

``FOURDGS_TRACEBACK=1`` shows the full traceback instead. This module imports no torch, so train.py
can refuse a model folder before torch loads (run_folder.precheck_model_folder).
"""
from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path
from typing import Callable

from baselines.run_folder import TrainingInterrupted, current_run, last_checkpoint


def has_flag(argv: list[str], *names: str) -> bool:
    """Whether any of `names` is typed (``--x`` or ``--x=...``)."""
    return any(a == n or a.startswith(n + "=") for a in argv for n in names)


def flag_value(argv: list[str], *names: str) -> str | None:
    """The last value of a single-valued flag (``-s X`` or ``-s=X``), or None."""
    value = None
    for i, arg in enumerate(argv):
        for name in names:
            if arg == name and i + 1 < len(argv):
                value = argv[i + 1]
            elif arg.startswith(name + "="):
                value = arg.split("=", 1)[1]
    return value


def resume_command(argv: list[str], model_path: Path, checkpoint: Path | None) -> str:
    """The train.py command that continues a run from `checkpoint`: its argv as typed, with -m and
    --start_checkpoint set and --overwrite dropped."""
    kept: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg in ("-m", "--model_path", "--start_checkpoint"):
            skip = True
            continue
        if arg == "--overwrite" or arg.startswith(("--model_path=", "-m=", "--start_checkpoint=")):
            continue
        kept.append(arg)
    tail = ["-m", str(model_path)] + (["--start_checkpoint", str(checkpoint)] if checkpoint else [])
    return shlex.join(["python", "train.py", *kept, *tail])


def interrupted_line(exc: BaseException) -> str:
    """One line after Ctrl-C: where the run stopped, its last checkpoint, how to resume."""
    run = current_run()
    if run is None:
        return "interrupted; nothing was saved"
    if isinstance(exc, TrainingInterrupted):
        where, checkpoint = f"at {exc.stage} iteration {exc.iteration}", exc.checkpoint
    else:  # a second Ctrl-C (or one outside the training loop): the last checkpoint written
        where = f"({run.record.get('stopped_at') or 'before the first save'})"
        checkpoint = last_checkpoint(run.path)
    if checkpoint is None:
        return (f"interrupted {where}; no checkpoint in {run.path} (--checkpoint_iterations writes them): "
                "rerun with --overwrite to start again")
    return f"interrupted {where}; last checkpoint {checkpoint}; resume: {resume_command(run.command[1:], run.path, checkpoint)}"


def run_cli(entry: Callable[[], int]) -> None:
    """Run `entry` and end the process as the module docstring says."""
    try:
        sys.exit(entry())
    except (ValueError, OSError, FloatingPointError, MemoryError) as exc:
        if os.environ.get("FOURDGS_TRACEBACK"):
            raise
        text = str(exc).strip()
        message = text.splitlines()[0] if text else type(exc).__name__
        if isinstance(exc, MemoryError):
            message = f"out of memory ({message}): lower -r/--resolution or the number of Gaussians"
        print(f"error: {message}", file=sys.stderr)
        sys.exit(2)
    except (TrainingInterrupted, KeyboardInterrupt) as exc:
        if os.environ.get("FOURDGS_TRACEBACK"):
            raise
        print(interrupted_line(exc), file=sys.stderr)
        sys.exit(128 + getattr(exc, "signum", 2))  # 130 after Ctrl-C, 143 after SIGTERM
