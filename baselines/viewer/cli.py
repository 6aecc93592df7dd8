"""`python view.py -m RUN [-m RUN_B] [--port P]`: the web viewer of trained runs.

    python view.py -m output/skating                                  # one run
    python view.py -m output/suite/skating/baseline -m output/suite/skating/reflow   # side by side
    python view.py -m RUN --port 8081 --max_res 768 --mode depth --time 0.5 [--iteration N] [--backend cpu]

Listens on 127.0.0.1 only and prints the URL (from another machine: `ssh -L 8080:localhost:8080`).
Render flags of render.py (`--iteration`, `--backend`, `--time_outside`, ...) apply to every run.
Bad input gives one `error:` line (exit code 2) before anything is loaded: a folder that is not
a trained run, a port in use, more than two runs; an unknown --mode once the runs are loaded.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time

from baselines.fourdgs.app import require_run

from .app import MAX_SIDE_RANGE, ViewerApp, check_port_free
from .runs import ViewerRun


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    parser = argparse.ArgumentParser(prog="python view.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("-m", "--model_path", action="append", required=True,
                        help="trained run folder; give it twice for two runs side by side")
    parser.add_argument("--port", type=int, default=8080, help="port on 127.0.0.1 (0: any free port)")
    parser.add_argument("--max_res", type=int, default=512, help="longer side of the still picture, in pixels")
    parser.add_argument("--mode", default="RGB", help="initial render mode (RGB, depth, alpha; ReFlow runs: 'full flow')")
    parser.add_argument("--color_scale", type=float, default=0.0,
                        help="flow speed (px) at full colour, one scale for both runs (0: each picture its own)")
    parser.add_argument("--no_frustums", action="store_true", help="start with the camera frustums hidden")
    parser.add_argument("--time", type=float, default=None, help="initial time in [0, 1] (default: the first training view's)")
    args, rest = parser.parse_known_args(argv)
    if len(args.model_path) > 2:
        raise ValueError(f"-m given {len(args.model_path)} times: the viewer shows one run or two side by side")
    low, high = MAX_SIDE_RANGE
    if not low <= args.max_res <= high:
        raise ValueError(f"--max_res must be in [{low}, {high}], got {args.max_res}")
    if not args.color_scale >= 0.0:
        raise ValueError(f"--color_scale must be >= 0, got {args.color_scale}")
    if args.time is not None and not 0.0 <= args.time <= 1.0:
        raise ValueError(f"--time must be in [0, 1], got {args.time}")
    return args, rest


def main(argv: list[str] | None = None) -> int:
    started = time.perf_counter()
    args, render_argv = parse_args(list(sys.argv[1:] if argv is None else argv))
    for path in args.model_path:
        require_run(path)
    check_port_free(args.port)  # before the (long) loading
    logging.basicConfig(level=logging.WARNING, format="[%(name)s] %(message)s")
    runs = [ViewerRun.load(path, render_argv) for path in args.model_path]
    loaded = time.perf_counter() - started
    app = ViewerApp(runs, port=args.port, max_side=args.max_res, mode=args.mode, start_time=args.time,
                    frustums=not args.no_frustums, color_scale=args.color_scale)
    url = app.start()
    for run in runs:
        print(f"[view] {run.summary()} on {run.device}", flush=True)
    print(f"[view] ready in {time.perf_counter() - started:.1f} s (runs loaded in {loaded:.1f} s)", flush=True)
    print(f"[view] open {url} in a browser (localhost only; Ctrl-C stops)", flush=True)
    app.wait()
    return 0
