"""Ctrl-C (or SIGTERM) during training: finish the current iteration, save a checkpoint, stop with one line.

    with deferred_interrupt() as stop:        # around the training loop (main thread only)
        ... one iteration ...
        if stop.requested: save a checkpoint, raise TrainingInterrupted(stage, iteration, path)

A KeyboardInterrupt in the middle of an iteration (densification, an optimizer step) could leave
the model half-updated, so the first SIGINT only sets a flag that the loop reads between
iterations; a second SIGINT raises KeyboardInterrupt at once (the last checkpoint written then
is the one to resume from). SIGTERM (``kill``, a job scheduler's stop) is handled the same way; it
also replaces the crash handler pycolmap installs for it, which would dump a native stack instead.
Outside the main thread nothing is installed.
"""
from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Any, Iterator

from baselines.run_folder import TrainingInterrupted  # noqa: F401  (raised by the trainer)


HANDLED = (signal.SIGINT, signal.SIGTERM)
NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}


class StopFlag:
    """Set by the first SIGINT / SIGTERM (or `request()`, e.g. from a test); `signum` says which."""

    def __init__(self) -> None:
        self.requested = False
        self.signum = int(signal.SIGINT)

    def request(self, signum: int = signal.SIGINT) -> None:
        self.requested, self.signum = True, int(signum)


@contextmanager
def deferred_interrupt() -> Iterator[StopFlag]:
    """Install the two-step SIGINT handler for the duration of the block (see the module docstring)."""
    flag = StopFlag()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum: int, frame: Any) -> None:
        if flag.requested:
            raise KeyboardInterrupt
        flag.request(signum)
        name = NAMES.get(signum, f"signal {signum}")
        print(f"[train] {name}: stopping after this iteration and saving a checkpoint "
              f"({name} again to stop at once)", file=sys.stderr, flush=True)

    previous = {signum: signal.signal(signum, handler) for signum in HANDLED}
    try:
        yield flag
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)
