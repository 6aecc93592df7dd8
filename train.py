#!/usr/bin/env python3
"""Train the 4DGS baseline, optionally with plugins (ReFlow), on a dataset or the embedded scene.

    python train.py -s data/nvidia/Skating --plugin reflow
    python train.py -s data/nvidia/Skating                      # the 4DGS baseline, same loop
    python train.py -s ... --plugin reflow --disable full_flow,cam_flow
    python train.py -s ... --start_checkpoint output/old4dgs/point_cloud/iteration_14000
    python train.py                                             # no data: embedded synthetic scene

Every input is checked (flags, config files, plugins, components, dataset files) before the first
training iteration. The run ends with an evaluation of the held-out views (results.json), test
renders and a novel-time video in the 4DGS output layout.
"""
from __future__ import annotations

import sys

from baselines.thread_policy import apply_thread_policy

apply_thread_policy()  # before torch starts: passive OpenMP waits, threads from the CPUs available

from baselines.fourdgs.app import run_cli, train_from_argv  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    train_from_argv(sys.argv[1:] if argv is None else argv)
    return 0


if __name__ == "__main__":
    run_cli(main)
