"""`Camera`: one view of the dataset in our convention (see `geometry.py`)."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .errors import DatasetError


def _as_float_tensor(value: Tensor | np.ndarray, name: str, shape: tuple[int, ...]) -> Tensor:
    tensor = torch.as_tensor(value)
    if not tensor.is_floating_point():
        tensor = tensor.to(torch.float32)
    tensor = tensor.to(torch.float32)
    if tuple(tensor.shape) != shape:
        raise DatasetError(f"Camera.{name} has shape {tuple(tensor.shape)}, expected {shape}")
    if not torch.isfinite(tensor).all():
        raise DatasetError(f"Camera.{name} holds non-finite values")
    return tensor


@dataclass
class Camera:
    """A pinhole view at one time.

    Attributes:
        uid: index of the camera within its list (train, test or video).
        image_name: name of the image (unique within the scene; no extension).
        width, height: image size in pixels.
        K: [3,3] float32 intrinsics in pixels; pixel (row i, col j) is centred at (j+0.5, i+0.5).
        viewmat: [4,4] float32 world->camera, OpenCV axes (x right, y down, z forward).
        time: normalised time in [0, 1].
        image: [H,W,3] float32 in [0, 1], or None for render-only cameras.
        frame_index: position of the frame in the video (an integer time index).
        camera_id: which physical (rig) camera took the image.
        mask: [H,W] float32 motion mask (1 = dynamic) or None.
        disparity: [H,W] float32 disparity map (as stored by the dataset) or None.
        extras: other per-view tensors (e.g. "alpha" [H,W], "near_far" [2], "eval_mask" [H,W]: a
            ground-truth motion mask for evaluation only, when the dataset gives training none).
    """

    uid: int
    image_name: str
    width: int
    height: int
    K: Tensor
    viewmat: Tensor
    time: float
    image: Tensor | None = None
    frame_index: int = 0
    camera_id: int = 0
    mask: Tensor | None = None
    disparity: Tensor | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise DatasetError(f"Camera '{self.image_name}': bad size {self.width}x{self.height}")
        self.K = _as_float_tensor(self.K, "K", (3, 3))
        self.viewmat = _as_float_tensor(self.viewmat, "viewmat", (4, 4))
        self.time = float(self.time)
        if not 0.0 <= self.time <= 1.0:
            raise DatasetError(f"Camera '{self.image_name}': time {self.time} outside [0, 1]")
        hw = (self.height, self.width)
        if self.image is not None:
            self.image = _as_float_tensor(self.image, "image", (*hw, 3))
        if self.mask is not None:
            self.mask = _as_float_tensor(self.mask, "mask", hw)
        if self.disparity is not None:
            self.disparity = _as_float_tensor(self.disparity, "disparity", hw)

    @property
    def camera_center(self) -> Tensor:
        """[3] camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    @property
    def evaluation_mask(self) -> Tensor | None:
        """[H,W] motion mask the evaluation's region metrics use: the dataset's ground-truth-only
        mask (extras["eval_mask"]) when it has one (truth beats an estimate, e.g. a prepared clip's
        auto masks next to its annotations), else the training mask, else None."""
        truth = self.extras.get("eval_mask")
        return truth if truth is not None else self.mask

    @property
    def device(self) -> torch.device:
        return self.viewmat.device

    def to(self, device: torch.device | str) -> "Camera":
        """A copy with every tensor on `device` (no re-validation, so no device sync)."""
        moved = copy.copy(self)
        for name in ("K", "viewmat", "image", "mask", "disparity"):
            value = getattr(self, name)
            setattr(moved, name, None if value is None else value.to(device))
        moved.extras = {k: v.to(device) for k, v in self.extras.items()}
        return moved
