"""A trained run as the viewer sees it: cameras, times, selections and render modes.

    run = ViewerRun.load("output/skating")              # or ViewerRun(loaded_run) from app.load_run
    picture, caption = run.render(viewmat, K, W, H, time=0.5, mode="depth", selection="dynamic only")

Renders go through the project's `rasterize()` (backend of the run's `--backend`, `auto` = gsplat
on a CUDA device, the CPU kernel otherwise). The Gaussians of the last few (time, selection)
pairs are cached, so moving the camera at a fixed time costs one rasterization per frame and no
deformation. Selections: "both"; "static only" / "dynamic only" split the Gaussians by the
model's deformation table (ReFlow's labels); they are offered when the table is mixed (a 4DGS
baseline deforms every Gaussian, so it has no static part). Modes: RGB, depth, alpha, plus the
run's plugins' `viewer_modes()` (ReFlow: "full flow" towards t + dt).
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from baselines.fourdgs.app import LoadedRun, load_run, require_run
from baselines.fourdgs.state import GaussianState

from .frame import MODES, ViewerMode, ViewFrame

SELECTIONS = ("both", "static only", "dynamic only")
CACHE_SIZE = 4  # deformed states kept (a frame and its t + dt, for two selections)


class ViewerRun:
    """One loaded run; thread-safe `render` (one render at a time per run)."""

    def __init__(self, loaded: LoadedRun) -> None:
        self.loaded = loaded
        trainer = loaded.trainer
        self.model = trainer.ctx.model
        self.path = Path(trainer.ctx.model_path)
        self.name = self.path.name
        self.iteration = loaded.iteration
        self.backend = loaded.args.pipe.backend
        self.background = trainer.ctx.background
        self.train_cameras = list(trainer.train_cameras)
        self.test_cameras = list(trainer.test_cameras)
        frames = max(int(trainer.ctx.scene.num_frames or 0), 2)
        self.dt = 1.0 / (frames - 1)
        table = self.model.deformation_table
        self.num_dynamic = int(table.sum())
        self.has_split = 0 < self.num_dynamic < self.model.num_gaussians
        self.modes: dict[str, ViewerMode] = dict(MODES)
        for plugin in trainer.hooks.plugins:
            self.modes.update(plugin.viewer_modes())
        self._rows = {"static only": (~table).nonzero().squeeze(1), "dynamic only": table.nonzero().squeeze(1)}
        self._cache: OrderedDict[tuple[float, str], GaussianState] = OrderedDict()
        self._lock = threading.RLock()

    @classmethod
    def load(cls, path: str | Path, extra_argv: list[str] | None = None) -> ViewerRun:
        require_run(path)
        return cls(load_run(["-m", str(path), *(extra_argv or [])]))

    @property
    def device(self) -> torch.device:
        return self.model.device

    @property
    def num_gaussians(self) -> int:
        return self.model.num_gaussians

    def summary(self) -> str:
        split = f", {self.num_dynamic} dynamic" if self.has_split else ""
        return f"{self.name} (iteration {self.iteration}, {self.num_gaussians} Gaussians{split})"

    def states(self, time: float, selection: str = "both") -> GaussianState:
        """The selected Gaussians deformed to `time` (cached)."""
        if selection not in SELECTIONS:
            raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")
        key = (round(float(time), 6), selection)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
            with torch.no_grad():
                state = self.model.deform(float(time), "fine").detach()
                if selection != "both" and self.has_split:
                    state = state.index(self._rows[selection])
            self._cache[key] = state
            while len(self._cache) > CACHE_SIZE:
                self._cache.popitem(last=False)
            return state

    @torch.no_grad()
    def render(self, viewmat: Tensor, K: Tensor, width: int, height: int, time: float, mode: str = "RGB",
               selection: str = "both", mode_fn: ViewerMode | None = None,
               color_scale: float = 0.0) -> tuple[np.ndarray, str]:
        """[H, W, 3] uint8 RGB picture and a caption of the run from a camera at `time`.

        `mode_fn` renders a mode this run's plugins do not provide (another run's, side by side).
        """
        fn = mode_fn or self.modes.get(mode)
        if fn is None:
            raise ValueError(f"{self.name}: no render mode {mode!r} (modes: {', '.join(self.modes)})")
        with self._lock:
            if selection != "both" and self.has_split and self._rows[selection].numel() == 0:
                return np.zeros((height, width, 3), np.uint8), f"no {selection.split()[0]} Gaussian"
            frame = ViewFrame(deform=lambda t: self.states(t, selection), time=float(time), dt=self.dt,
                              viewmat=viewmat.to(self.device, torch.float32), K=K.to(self.device, torch.float32),
                              width=int(width), height=int(height), backend=self.backend,
                              background=self.background, sh_degree=self.model.active_sh_degree,
                              color_scale=float(color_scale))
            return fn(frame)
