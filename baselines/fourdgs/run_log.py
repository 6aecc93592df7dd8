"""Training log: a JSON-lines file, a progress bar, and per-phase timers.

`train_log.jsonl` gets one object per logged iteration ({"kind": "iter", stage, iteration, losses,
psnr, num_gaussians, it_per_s, ...}) and one per event (stage start, test, save, checkpoint). Lines
are flushed as written, so a killed run keeps its log.

Each line is one ``write`` on an ``O_APPEND`` descriptor; a write that fails or is cut short (a
full disk, a file-size limit) is undone by truncating the file back to where the line began, and
raised as an ``OSError`` naming the file, so the log never ends in a torn line. `read_log` is the
tolerant reader: a cut-off last line (a log from elsewhere, or a power cut) is skipped with a
warning, a broken line in the middle is an error naming the file and line.
"""
from __future__ import annotations

import json
import logging
import os
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any, Iterator

from tqdm import tqdm


class StageTimer:
    """Accumulates wall time per named phase (deform_project, rasterize, loss_backward, ...)."""

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.count: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.total[name] += time.perf_counter() - start
            self.count[name] += 1

    def means(self) -> dict[str, float]:
        """Mean milliseconds per call of each phase."""
        return {k: 1000.0 * self.total[k] / max(1, self.count[k]) for k in self.total}


PRINTED_EVENTS = ("test", "saved", "checkpoint", "resumed", "loaded", "train_end", "final_stretch")
PLAIN_PROGRESS_EVERY = 100  # iterations between progress lines when stderr is not a terminal


def _is_terminal(stream: IO[str]) -> bool:
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


class _Progress:
    """A tqdm bar on a terminal; elsewhere (log files, CI) one plain line every N iterations.

    A bar redrawn with carriage returns floods a log file; ``every`` (default
    PLAIN_PROGRESS_EVERY) sets the spacing of the plain lines, the stage's last iteration included.
    """

    def __init__(self, total: int, initial: int, desc: str, quiet: bool, stream: IO[str] | None = None,
                 every: int = PLAIN_PROGRESS_EVERY) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.total, self.desc, self.every = total, desc, max(1, every)
        plain = quiet or not _is_terminal(self.stream)
        self.bar = None if plain else tqdm(total=total, initial=initial, desc=desc, dynamic_ncols=True,
                                           file=self.stream)
        self.quiet = quiet
        self.ema_loss: float | None = None

    def update(self, ctx: Any) -> None:
        if self.quiet:
            return
        loss = float(ctx.metrics.get("loss", float("nan")))
        self.ema_loss = loss if self.ema_loss is None else 0.4 * loss + 0.6 * self.ema_loss
        postfix = dict(loss=f"{self.ema_loss:.5f}", psnr=f"{ctx.metrics.get('psnr', 0):.2f}",
                       points=ctx.metrics.get("num_gaussians", 0))
        if self.bar is None:
            if ctx.iteration % self.every == 0 or ctx.iteration == self.total:
                fields = " ".join(f"{k}={v}" for k, v in postfix.items())
                print(f"[{self.desc}] {ctx.iteration}/{self.total} {fields}", file=self.stream, flush=True)
            return
        self.bar.update(1)
        if ctx.iteration % 10 == 0:
            self.bar.set_postfix(**postfix)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class RunLog:
    """Writes train_log.jsonl and drives the progress bar."""

    def __init__(self, path: Path, quiet: bool = False) -> None:
        self.path = path
        self.quiet = quiet
        try:
            self.fd: int | None = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        except OSError as err:
            raise OSError(err.errno, err.strerror, str(path)) from None
        self.last_time = time.perf_counter()
        self.last_iteration = 0

    def progress(self, total: int, initial: int, desc: str, **kwargs: Any) -> _Progress:
        """A progress display for one stage (kwargs: ``stream``, ``every``; see _Progress)."""
        return _Progress(total, initial, desc, self.quiet, **kwargs)

    def _write(self, record: dict[str, Any]) -> None:
        if self.fd is None:
            raise ValueError(f"{self.path}: the log was closed")
        append_line(self.fd, json.dumps(record, default=str), self.path)

    def event(self, kind: str, **fields: Any) -> None:
        self._write({"kind": kind, "time": time.time(), **fields})
        if not self.quiet and kind in PRINTED_EVENTS:
            tqdm.write(f"[{kind}] " + ", ".join(f"{k}={_short(v)}" for k, v in fields.items()))

    def iteration(self, ctx: Any, every: int) -> None:
        if every <= 0 or ctx.iteration % every != 0:
            return
        now = time.perf_counter()
        steps = max(1, ctx.iteration - self.last_iteration) if ctx.iteration > self.last_iteration else every
        rate = steps / max(now - self.last_time, 1e-9)
        self.last_time, self.last_iteration = now, ctx.iteration
        self._write({
            "kind": "iter", "stage": ctx.stage, "iteration": ctx.iteration,
            "losses": {k: float(v.detach()) for k, v in ctx.losses.items()},
            "it_per_s": rate, **ctx.metrics,
        })

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def append_line(fd: int, text: str, path: Path) -> None:
    """Append ``text + "\\n"`` to the O_APPEND descriptor `fd` whole, or not at all (OSError naming `path`)."""
    data = (text + "\n").encode("utf-8")
    start = os.fstat(fd).st_size
    try:
        written = os.write(fd, data)
        if written != len(data):  # a file-size limit or a full disk cut it short
            raise OSError(27, "File too large or disk full: the line was cut short")
    except OSError as err:
        try:
            os.ftruncate(fd, start)
        except OSError:  # best effort; readers skip a torn last line with a warning anyway
            pass
        raise OSError(err.errno, err.strerror or str(err), str(path)) from None


def read_log(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The records of a train_log.jsonl; a torn last line is skipped with a warning (ValueError naming
    the file and line for a broken line elsewhere)."""
    path = Path(path)
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    records = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except ValueError:
            if number == len(lines):
                logging.getLogger("train").warning("%s: last line %d is cut off (a write that did not finish); "
                                                   "skipped", path, number)
                continue
            raise ValueError(f"{path}: line {number} is not JSON") from None
    return records


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_short(v)}" for k, v in value.items()) + "}"
    return str(value)
