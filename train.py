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

from baselines.cli_exit import run_cli  # noqa: E402  (no torch: the checks below come first)
from baselines.run_folder import precheck_model_folder  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    precheck_model_folder(argv)  # a typed -m that cannot take this run is refused before torch loads
    from baselines.fourdgs.app import train_from_argv

    train_from_argv(argv)
    return 0


if __name__ == "__main__":
    run_cli(main)
