#!/usr/bin/env python3
"""Render a trained model (4DGS's render.py): test/train views with metrics, depth, video.

    python render.py -m output/balloon [--iteration N] [--skip_train] [--skip_test] [--skip_video]

The training run's configuration (dataset, plugins, components) is read back from the model
directory (config.json, else 4DGS's cfg_args); flags given here override it, except that the
model's shape (net_width, defor_depth, kplanes_config, sh_degree, ...) is fixed by its saved files:
a load that fails names the shape flags given here.
"""
from __future__ import annotations

import sys

from baselines.thread_policy import apply_thread_policy

apply_thread_policy()  # before torch starts: passive OpenMP waits, threads from the CPUs available

from baselines.fourdgs.app import render_from_argv, run_cli  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    render_from_argv(sys.argv[1:] if argv is None else argv)
    return 0


if __name__ == "__main__":
    run_cli(main)
