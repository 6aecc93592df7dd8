"""Progress output: a bar on a terminal, spaced plain lines in a log file."""
from __future__ import annotations

import io
from types import SimpleNamespace

from baselines.fourdgs.run_log import RunLog


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _drive(stream, total=250, every=100):
    log = RunLog.__new__(RunLog)  # progress() needs only .quiet
    log.quiet = False
    bar = log.progress(total, 0, "fine", stream=stream, every=every)
    for iteration in range(1, total + 1):
        bar.update(SimpleNamespace(iteration=iteration, metrics={"loss": 0.1, "psnr": 20.0, "num_gaussians": 7}))
    bar.close()
    return stream.getvalue()


def test_non_terminal_progress_is_one_line_every_n_iterations():
    text = _drive(io.StringIO())
    assert "\r" not in text
    lines = text.splitlines()
    assert [line.split()[1] for line in lines] == ["100/250", "200/250", "250/250"]
    assert lines[0] == "[fine] 100/250 loss=0.10000 psnr=20.00 points=7"


def test_terminal_progress_is_a_bar():
    assert "\r" in _drive(_Terminal())
