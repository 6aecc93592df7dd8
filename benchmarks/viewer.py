"""What the web viewer costs: loading, one frame per render mode, playing, and (with --browser)
the time to the first frame in a real headless Chromium.

    python benchmarks/viewer.py -m output/skating_reflow [-m output/skating_base] [--res 512] [--frames 15] [--browser]

Frames are rendered the way the viewer renders them (ViewerRun.render) from the first training
camera's pose with a 4:3 canvas whose longer side is --res (the viewer's default still picture:
512 x 384), at a fixed time (the deformed Gaussians cached, as while the camera moves) and with
the time advancing every frame (playing: one deformation per frame). Medians over --frames
frames after one warm-up; CPU is the process's CPU time per frame (all threads). With --browser,
`view.py` is started in a subprocess and Chromium opens it: seconds from the command's start to
the server's "ready" line, to the first frame sent, and to a screenshot that shows it.
Prints a markdown table and the machine's load average.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()

import numpy as np  # noqa: E402
import torch  # noqa: E402

from baselines.viewer.camera import image_size, intrinsics, vertical_fov  # noqa: E402
from baselines.viewer.runs import ViewerRun  # noqa: E402


def timed(fn, frames: int) -> tuple[float, float]:
    """(median wall ms, median CPU ms) of `fn(k)` over `frames` calls after one warm-up."""
    fn(-1)
    walls, cpus = [], []
    for k in range(frames):
        wall, cpu = time.perf_counter(), time.process_time()
        fn(k)
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return statistics.median(walls) * 1e3, statistics.median(cpus) * 1e3


def frame_rows(run: ViewerRun, res: int, frames: int) -> list[tuple[str, str, float, float]]:
    cam = run.train_cameras[0]
    width, height = image_size(4 / 3, res)
    K = intrinsics(vertical_fov(cam.K, cam.height), width, height)
    rows = []
    for mode in run.modes:
        wall, cpu = timed(lambda k: run.render(cam.viewmat, K, width, height, cam.time, mode), frames)
        rows.append((f"{mode}, fixed time", f"{width}x{height}", wall, cpu))
    times = np.linspace(0.0, 1.0, frames + 1)
    wall, cpu = timed(lambda k: run.render(cam.viewmat, K, width, height, float(times[k]) if k >= 0 else 0.5), frames)
    rows.append(("RGB, time advancing (play)", f"{width}x{height}", wall, cpu))
    low_w, low_h = image_size(4 / 3, 192)
    low_K = intrinsics(vertical_fov(cam.K, cam.height), low_w, low_h)
    wall, cpu = timed(lambda k: run.render(cam.viewmat, low_K, low_w, low_h, cam.time), frames)
    rows.append(("RGB, fixed time (moving size)", f"{low_w}x{low_h}", wall, cpu))
    return rows


def browser_row(paths: list[str], res: int) -> dict[str, float]:
    """Seconds to "ready", to the first frame sent and to a screenshot showing it (view.py + Chromium)."""
    from benchmarks.headless_browser import HeadlessChromium, ViewerProcess, blank_reason

    start = time.perf_counter()
    args = [a for p in paths for a in ("-m", p)]
    proc = ViewerProcess(*args, "--port", "0", "--max_res", str(res))
    try:
        url = proc.wait_for(r"open (http://127\.0\.0\.1:\d+) ").group(1)
        ready = time.perf_counter() - start
        with HeadlessChromium(url, 1280, 800) as browser:
            sent = proc.wait_for(r"first frame .* sent ([\d.]+) s after it connected", timeout=300)
            first = time.perf_counter() - start
            region = (slice(240, 680), slice(150, 700))
            browser.wait_for_picture(lambda p: blank_reason(p[region]) is None, timeout=300)
            shown = time.perf_counter() - start
    finally:
        proc.stop()
    return {"ready": ready, "first_frame": first, "after_connect": float(sent.group(1)), "shown": shown}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-m", "--model_path", action="append", required=True)
    parser.add_argument("--res", type=int, default=512)
    parser.add_argument("--frames", type=int, default=15)
    parser.add_argument("--browser", action="store_true")
    args = parser.parse_args(argv)
    print(f"load average before: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}; "
          f"torch threads {torch.get_num_threads()}")
    print("| run | what | size | ms / frame | FPS | CPU ms / frame |\n|---|---|---|---:|---:|---:|")
    for path in args.model_path:
        wall, cpu = time.perf_counter(), time.process_time()
        run = ViewerRun.load(path)
        load_wall, load_cpu = time.perf_counter() - wall, time.process_time() - cpu
        print(f"| {run.name} ({run.num_gaussians} Gaussians) | load | | {load_wall * 1e3:.0f} | | {load_cpu * 1e3:.0f} |")
        for what, size, wall_ms, cpu_ms in frame_rows(run, args.res, args.frames):
            print(f"| {run.name} | {what} | {size} | {wall_ms:.0f} | {1e3 / wall_ms:.1f} | {cpu_ms:.0f} |")
    if args.browser:
        seconds = browser_row(args.model_path, args.res)
        print(f"\nview.py + headless Chromium: ready {seconds['ready']:.1f} s, first frame sent {seconds['first_frame']:.1f} s "
              f"({seconds['after_connect']:.2f} s after the browser connected), shown in a screenshot "
              f"{seconds['shown']:.1f} s after the command started")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
