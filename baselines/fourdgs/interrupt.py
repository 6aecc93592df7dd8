"""Ctrl-C during training: finish the current iteration, save a checkpoint, stop with one line.

    with deferred_interrupt() as stop:        # around the training loop (main thread only)
        ... one iteration ...
        if stop.requested: save a checkpoint, raise TrainingInterrupted(stage, iteration, path)

A KeyboardInterrupt in the middle of an iteration (densification, an optimizer step) could leave
the model half-updated, so the first SIGINT only sets a flag that the loop reads between
iterations; a second SIGINT raises KeyboardInterrupt at once (the last checkpoint written then
is the one to resume from). Outside the main thread nothing is installed.
"""
from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Any, Iterator

from baselines.run_folder import TrainingInterrupted  # noqa: F401  (raised by the trainer)


class StopFlag:
    """Set by the first SIGINT (or `request()`, e.g. from a test)."""

    def __init__(self) -> None:
        self.requested = False

    def request(self) -> None:
        self.requested = True


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
        flag.request()
        print("[train] Ctrl-C: stopping after this iteration and saving a checkpoint "
              "(Ctrl-C again to stop at once)", file=sys.stderr, flush=True)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)
