"""Drive a headless Chromium (Debian's `chromium` package) through its DevTools protocol.

    with HeadlessChromium("http://127.0.0.1:8080", width=1280, height=800) as browser:   # RuntimeError if it cannot start
        png = browser.screenshot()                                 # PNG bytes
        picture = browser.wait_for_picture(is_ready, timeout=60)   # [H, W, 3] uint8 RGB

Used by the viewer's browser test, `benchmarks/viewer.py` and the screenshots in docs/VIEWER.md, with
`ViewerProcess` (view.py in a subprocess, its output read line by line). Only the
standard library and `websockets` (a requirement of viser) are needed; no browser download.
Chromium runs with a fresh profile and without any background network traffic or GPU:
`--headless --no-sandbox --disable-gpu --disable-quic --no-first-run
--disable-background-networking --disable-component-update --disable-sync`, plus
`--enable-unsafe-swiftshader`, the software WebGL that viser's three.js canvas needs without a GPU,
and `--disable-dev-shm-usage` (containers often have a tiny /dev/shm).
"""
from __future__ import annotations

import base64
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from websockets.sync.client import connect

ROOT = Path(__file__).resolve().parents[1]
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-unsafe-swiftshader", "--disable-dev-shm-usage", "--hide-scrollbars", "--mute-audio")


def chromium_binary() -> str | None:
    """Path of a Chromium executable, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


def blank_reason(picture: np.ndarray, min_std: float = 8.0, min_share: float = 0.05) -> str | None:
    """Why a screenshot [H, W, 3] looks blank (None when it does not): almost one colour, or
    fewer than `min_share` of its pixels away from the most common colour."""
    grey = cv2.cvtColor(picture, cv2.COLOR_RGB2GRAY).astype(np.float64)
    if grey.std() < min_std:
        return f"grey-level std {grey.std():.1f} < {min_std}"
    values, counts = np.unique(picture.reshape(-1, 3) // 8, axis=0, return_counts=True)
    mode = values[np.argmax(counts)]
    share = float((np.abs(picture.reshape(-1, 3) // 8 - mode).max(1) > 1).mean())
    if share < min_share:
        return f"only {share:.1%} of the pixels differ from the background colour"
    return None


class HeadlessChromium:
    """A headless Chromium showing one page (opened at start: a navigation later would swap the
    page's target), controlled over the DevTools websocket."""

    def __init__(self, url: str, width: int = 1280, height: int = 800, start_timeout: float = 30.0) -> None:
        binary = chromium_binary()
        if binary is None:
            raise RuntimeError("no chromium executable on PATH (apt-get install chromium)")
        self.profile = Path(tempfile.mkdtemp(prefix="headless-chromium-"))
        self.process = subprocess.Popen(
            [binary, *FLAGS, f"--user-data-dir={self.profile}", "--remote-debugging-port=0",
             f"--window-size={width},{height}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self._id = 0
        try:
            port = self._devtools_port(start_timeout)
            targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
            page = next(t for t in targets if t.get("type") == "page")
            self.socket = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
        except Exception:
            self.close()
            raise
        self.call("Page.enable")
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def _devtools_port(self, timeout: float) -> int:
        marker = self.profile / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"chromium exited at start (code {self.process.returncode})")
            if marker.is_file() and marker.read_text().strip():
                return int(marker.read_text().split()[0])
            time.sleep(0.1)
        raise RuntimeError(f"chromium did not open its DevTools port within {timeout:.0f} s")

    def call(self, method: str, timeout: float = 30.0, **params) -> dict:
        """Send one DevTools command and return its result (events in between are skipped)."""
        self._id += 1
        self.socket.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            message = json.loads(self.socket.recv(timeout=max(0.1, deadline - time.monotonic())))
            if message.get("id") == self._id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})

    def screenshot(self) -> bytes:
        """PNG bytes of the page as it is now."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def picture(self) -> np.ndarray:
        """[H, W, 3] uint8 RGB screenshot."""
        bgr = cv2.imdecode(np.frombuffer(self.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def wait_for_picture(self, ready: Callable[[np.ndarray], bool], timeout: float = 60.0,
                         interval: float = 0.5) -> np.ndarray:
        """Screenshots until `ready(picture)`; returns that picture (TimeoutError with the last one's reason)."""
        deadline = time.monotonic() + timeout
        while True:
            picture = self.picture()
            if ready(picture):
                return picture
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page did not become ready within {timeout:.0f} s ({blank_reason(picture)})")
            time.sleep(interval)

    def click_close_buttons(self, text: str) -> bool:
        """Click the close button of the element showing `text` (e.g. a notification); True if found."""
        script = f"""(() => {{
          const leaves = Array.from(document.querySelectorAll('*'))
            .filter(e => e.children.length === 0 && e.textContent.includes({json.dumps(text)}));
          for (let e = leaves[0], i = 0; e && i < 8; e = e.parentElement, i++) {{
            const button = e.querySelector('button');
            if (button) {{ button.click(); return true; }}
          }}
          return false;
        }})()"""
        return bool(self.call("Runtime.evaluate", expression=script, returnByValue=True)["result"].get("value"))

    def close(self) -> None:
        sock = getattr(self, "socket", None)
        if sock is not None:
            sock.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> HeadlessChromium:
        return self

    def __exit__(self, *_) -> None:
        self.close()


class ViewerProcess:
    """`python view.py ARGS` with its output read line by line in a thread."""

    def __init__(self, *args: str) -> None:
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        self.process = subprocess.Popen([sys.executable, "view.py", *args], cwd=ROOT, env=env, text=True,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.put(line)

    def wait_for(self, pattern: str, timeout: float = 120.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.process.poll() is not None and self.lines.empty():
                    break
                continue
            self.output.append(line)
            found = re.search(pattern, line)
            if found:
                return found
        raise AssertionError(f"no line matching {pattern!r}; output so far:\n{''.join(self.output)}")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=20)
