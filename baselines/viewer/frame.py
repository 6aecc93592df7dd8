"""What a viewer render mode receives, and the host's own modes (RGB, depth, alpha).

    frame = ViewFrame(deform=run.states, time=t, dt=1 / 35, viewmat=..., K=..., width=W, height=H,
                      backend="auto", background=torch.ones(3), sh_degree=3)
    picture, caption = MODES["depth"](frame)          # [H, W, 3] uint8 RGB, a short caption ("" for none)

A mode is any callable `ViewFrame -> (picture, caption)`. Plugins add their own through
`Plugin.viewer_modes()` (baselines/fourdgs/plugins.py), e.g. ReFlow's rendered full flow
towards t + dt; the frame hands them the Gaussians at any time (`frame.deform(t)`, with the
viewer's static/dynamic selection already applied), so a mode needs no access to the model.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
import torch
from torch import Tensor

from baselines.fourdgs.evaluate import depth_to_color
from baselines.fourdgs.state import GaussianState
from baselines.render import rasterize
from baselines.render.sh import sh_to_rgb


@dataclass
class ViewFrame:
    """One viewer frame: a camera (OpenCV, pixels) at a time, and the Gaussians to draw.

    Attributes:
        deform: time -> GaussianState of the Gaussians shown (selection applied, cached).
        time: the frame's time; dt: one frame of the run's video (1 / (frames - 1)).
        viewmat: [4, 4] world-to-camera; K: [3, 3] intrinsics for width x height.
        background: [3] RGB in [0, 1]; sh_degree: the model's active SH degree.
        color_scale: the magnitude at which modes that colour a magnitude saturate (the flow's
            speed in px): one scale for two runs side by side; 0 = each picture its own.
    """

    deform: Callable[[float], GaussianState]
    time: float
    dt: float
    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    backend: str
    background: Tensor
    sh_degree: int
    color_scale: float = 0.0

    @property
    def state(self) -> GaussianState:
        return self.deform(self.time)

    @property
    def camera_center(self) -> Tensor:
        """[3] world position of the camera."""
        return torch.linalg.inv(self.viewmat)[:3, 3]


ViewerMode = Callable[[ViewFrame], "tuple[np.ndarray, str]"]


def rasterize_frame(frame: ViewFrame) -> tuple[Tensor, Tensor, Tensor]:
    """(rgb [H, W, 3], depth [H, W, 1], alpha [H, W, 1]) of the frame's Gaussians at its time."""
    state = frame.state
    colors = sh_to_rgb(state.shs, state.means, frame.camera_center, frame.sh_degree)
    image, depth, alpha, _ = rasterize(state.means, state.quats, state.scales, state.opacities, colors,
                                       frame.viewmat, frame.K, frame.width, frame.height, backend=frame.backend,
                                       background=frame.background)
    return image, depth, alpha


def to_rgb8(image: Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> uint8 RGB."""
    return (image.detach().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def rgb_mode(frame: ViewFrame) -> tuple[np.ndarray, str]:
    return to_rgb8(rasterize_frame(frame)[0]), ""


def depth_mode(frame: ViewFrame) -> tuple[np.ndarray, str]:
    """Expected depth, inverse depth colour-mapped (turbo, near = red), empty pixels black."""
    _, depth, alpha = rasterize_frame(frame)
    covered = depth[alpha > 0.5]
    caption = f"depth {float(covered.min()):.2f}-{float(covered.max()):.2f}" if covered.numel() else "depth: empty"
    return cv2.cvtColor(depth_to_color(depth, alpha), cv2.COLOR_BGR2RGB), caption


def alpha_mode(frame: ViewFrame) -> tuple[np.ndarray, str]:
    """Accumulated opacity as grey levels (white = opaque)."""
    alpha = rasterize_frame(frame)[2]
    return to_rgb8(alpha.expand(-1, -1, 3)), ""


MODES: dict[str, ViewerMode] = {"RGB": rgb_mode, "depth": depth_mode, "alpha": alpha_mode}
