#!/usr/bin/env python3
"""A screenshot of the web viewer in headless Chromium (the pictures of docs/VIEWER.md).

    python scripts/viewer_screenshot.py -m output/skating_reflow -o docs/images/viewer_reflow.png \\
        [-m RUN_B] [--mode "full flow"] [--time 0.5] [--size 1280x800] [--max_res 512] [--no_frustums]

Starts `view.py` on a free port, opens it in Debian's headless Chromium (benchmarks/
headless_browser.py), waits for the first frame, closes viser's "software WebGL" notice, waits
`--settle` seconds and writes the PNG. Needs `apt-get install chromium`.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.headless_browser import HeadlessChromium, ViewerProcess, blank_reason  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-m", "--model_path", action="append", required=True)
    parser.add_argument("-o", "--out", type=Path, required=True)
    parser.add_argument("--mode", default="RGB")
    parser.add_argument("--time", type=float, default=None)
    parser.add_argument("--size", default="1280x800", help="browser window WxH")
    parser.add_argument("--max_res", type=int, default=512)
    parser.add_argument("--no_frustums", action="store_true")
    parser.add_argument("--color_scale", type=float, default=0.0)
    parser.add_argument("--settle", type=float, default=3.0, help="seconds to wait after the first frame")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    view_args = [a for p in args.model_path for a in ("-m", p)]
    view_args += ["--port", "0", "--max_res", str(args.max_res), "--mode", args.mode]
    view_args += ["--time", str(args.time)] if args.time is not None else []
    view_args += ["--no_frustums"] if args.no_frustums else []
    view_args += ["--color_scale", str(args.color_scale)]
    proc = ViewerProcess(*view_args)
    try:
        url = proc.wait_for(r"open (http://127\.0\.0\.1:\d+) ").group(1)
        with HeadlessChromium(url, width, height) as browser:
            proc.wait_for(r"first frame .* sent", timeout=300)
            browser.wait_for_picture(lambda p: blank_reason(p) is None, timeout=300)
            browser.click_close_buttons("Software WebGL")
            time.sleep(args.settle)
            picture = browser.picture()
    finally:
        proc.stop()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    print(f"[screenshot] {args.out} ({width}x{height}) of {url}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
