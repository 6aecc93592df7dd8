"""Per-browser render thread: low resolution while the view changes, full resolution once still.

    renderer = ClientRenderer(client, draw, max_side=lambda: 512, playing=lambda: False)
    renderer.start(); renderer.request(moving=True)      # on every camera message
    renderer.request(moving=False)                       # a setting changed (mode, time, ...)

`draw(width, height) -> [H, W, 3] uint8` renders the client's current view. While the camera moved
in the last STILL_AFTER seconds (or the time plays) a frame is drawn at the size the measured
render speed allows at MOVING_FPS (never above the full size, never below MIN_SIDE px on the
longer side); once the camera has been still for STILL_AFTER seconds the view is drawn once more
at full size (`max_side()` px on the longer side, the canvas' aspect). Requests that arrive
during a render are merged: the thread always draws the newest view, never a queue of stale ones.
The first frame sent is timed (`first_frame_s`, from the client's connection).
"""
from __future__ import annotations

import logging
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np
import viser

from .camera import image_size

log = logging.getLogger("view")
STILL_AFTER = 0.25  # s without camera motion before the full-resolution frame
MOVING_FPS = 8.0  # frame rate aimed at while the camera moves (sets the low resolution)
MIN_SIDE = 96  # px: the low resolution never goes below this on the longer side


@dataclass
class FrameRecord:
    width: int
    height: int
    seconds: float
    full: bool


class ClientRenderer(threading.Thread):
    """The render thread of one connected browser (see the module docstring)."""

    def __init__(self, client: viser.ClientHandle, draw: Callable[[int, int], np.ndarray],
                 max_side: Callable[[], int], playing: Callable[[], bool]) -> None:
        super().__init__(daemon=True, name=f"viewer-client-{client.client_id}")
        self.client = client
        self.draw = draw
        self.max_side = max_side
        self.playing = playing
        self.connected_at = time.perf_counter()
        self.first_frame_s: float | None = None
        self.records: deque[FrameRecord] = deque(maxlen=50)
        self._wake = threading.Event()
        self._dirty = False
        self._full_pending = False
        self._last_move = 0.0
        self._pixels_per_second: float | None = None
        self._running = True

    def request(self, moving: bool = False) -> None:
        """Ask for a new frame; `moving` marks camera motion (low resolution until still)."""
        if moving:
            self._last_move = time.perf_counter()
        self._dirty = True
        self._wake.set()

    def stop(self) -> None:
        self._running = False
        self._wake.set()

    def _moving(self) -> bool:
        return time.perf_counter() - self._last_move < STILL_AFTER or self.playing()

    def _size(self, full: bool) -> tuple[int, int]:
        aspect = self.client.camera.aspect
        side = int(self.max_side())
        if not full and self._pixels_per_second is not None:
            budget = self._pixels_per_second / MOVING_FPS  # pixels one frame may cost
            low = int((budget * max(aspect, 1.0 / aspect)) ** 0.5)
            side = min(side, max(MIN_SIDE, low))
        elif not full:
            side = min(side, 2 * MIN_SIDE)  # no measurement yet: start small
        return image_size(aspect, side)

    def run(self) -> None:
        while self._running:
            self._wake.wait(timeout=0.05)
            self._wake.clear()
            if not self._running:
                break
            moving = self._moving()
            if self._dirty:
                self._dirty = False
                self._render(full=not moving)
                self._full_pending = moving
            elif self._full_pending and not moving:
                self._full_pending = False
                self._render(full=True)

    def _render(self, full: bool) -> None:
        try:
            if self.client.camera.update_timestamp == 0.0:  # no camera message from the browser yet
                self._dirty = True
                return
            width, height = self._size(full)
            start = time.perf_counter()
            picture = self.draw(width, height)
            seconds = time.perf_counter() - start
            self.client.scene.set_background_image(picture, format="jpeg", jpeg_quality=90 if full else 60)
        except Exception:  # a broken frame must not kill the viewer: log it and wait for the next request
            log.error("render failed:\n%s", traceback.format_exc())
            return
        speed = width * height / max(seconds, 1e-6)
        self._pixels_per_second = speed if self._pixels_per_second is None else 0.5 * (self._pixels_per_second + speed)
        self.records.append(FrameRecord(width, height, seconds, full))
        if self.first_frame_s is None:
            self.first_frame_s = time.perf_counter() - self.connected_at
            print(f"[view] client {self.client.client_id}: first frame ({width}x{height}) sent "
                  f"{self.first_frame_s:.2f} s after it connected (render {seconds * 1e3:.0f} ms)", flush=True)
