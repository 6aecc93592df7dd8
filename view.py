#!/usr/bin/env python3
"""Web viewer of trained runs (viser): live renders from the browser's camera, a time slider,
the training cameras, static/dynamic selections and render modes; two runs side by side.

    python view.py -m output/skating [-m output/skating_reflow] [--port 8080]

See baselines/viewer/ (cli.py for the flags).
"""
from __future__ import annotations

import sys

from baselines.thread_policy import apply_thread_policy

apply_thread_policy()  # before torch starts: passive OpenMP waits, threads from the CPUs available

from baselines.fourdgs.app import run_cli  # noqa: E402
from baselines.viewer.cli import main as viewer_main  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    return viewer_main(sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    run_cli(main)
