"""What a real capture's priors look like: monocular disparity, world units, no motion masks.

    priors = Priors.real()                       # or Priors.parse("real"), Priors() = exact
    disparity = priors.disparity(depth, frame, seed)   # [H, W] float32, as disp/NNN.npy stores it

A real NVIDIA/DynamicNeRF capture ships `disp/*.npy` from a monocular network (MiDaS): inverse
depth up to an unknown per-frame affine map (1 / z = s_n d_n + o_n, a different s_n, o_n in every
frame), with a smooth, low-frequency error and soft depth edges; its world units are COLMAP's
(NVIDIA's near/far bounds are ~37-71, not ~1-10), and it has no motion masks. The exact mode
(`Priors()`, the default) writes disparity = 1 / depth and the ground-truth masks; `Priors.real()`
writes, per frame n (seeded by the scene seed and n):

    u   = 1 / z                                  metric inverse depth at the scene's scale
    u_b = blur(u, edge_blur_px)                  soft depth edges (a Gaussian blur of inverse depth)
    u_f = u_b * exp(bias * F_n)                  low-frequency error: F_n a unit-variance random field,
                                                 bicubically upsampled from a (bias_cells + 1)^2 grid
    d_n = s_n * u_f / median(u_f) + s_n * c_n    the network's output: no metric scale, an offset

with s_n log-uniform in `scale_range` and c_n uniform in `shift_range` (the shift in units of the
frame's median inverse depth). Pixels where d_n <= 0 carry no depth, as a network's far field.
`masks=False` leaves motion_masks/ out (a run then estimates them); the exact masks go to
gt/motion_masks/ for evaluation either way. Each effect is skipped when its parameter is 0.

`scene_scale` is not a prior but the capture's world unit: the simulator multiplies every
translation, depth and bound by it (images and flow are unchanged: scaling the whole world with
its cameras changes no pixel).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from ._validate import check_nonnegative

MODES = ("exact", "real")


@dataclass(frozen=True)
class Priors:
    """How disparity and masks are written (see the module docstring). Defaults: exact."""

    mode: str = "exact"
    scale_range: tuple = (1.0, 1.0)
    shift_range: tuple = (0.0, 0.0)
    bias: float = 0.0
    bias_cells: int = 3
    edge_blur_px: float = 0.0
    masks: bool = True

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"priors: unknown mode {self.mode!r} ({', '.join(MODES)})")
        lo, hi = (float(v) for v in self.scale_range)
        if not 0 < lo <= hi:
            raise ValueError(f"priors: scale_range must be 0 < low <= high, got {self.scale_range}")
        a, b = (float(v) for v in self.shift_range)
        if not a <= b:
            raise ValueError(f"priors: shift_range must be low <= high, got {self.shift_range}")
        object.__setattr__(self, "scale_range", (lo, hi))
        object.__setattr__(self, "shift_range", (a, b))
        object.__setattr__(self, "bias", check_nonnegative("priors.bias", self.bias))
        object.__setattr__(self, "edge_blur_px", check_nonnegative("priors.edge_blur_px", self.edge_blur_px))
        if int(self.bias_cells) < 1:
            raise ValueError(f"priors: bias_cells must be >= 1, got {self.bias_cells}")

    @classmethod
    def real(cls) -> "Priors":
        """A monocular network's disparity and no motion masks (the values in the module docstring)."""
        return cls(mode="real", scale_range=(0.3, 3.0), shift_range=(-0.2, 0.5), bias=0.05, bias_cells=3,
                   edge_blur_px=1.5, masks=False)

    @classmethod
    def parse(cls, name: str) -> "Priors":
        """`exact` or `real`."""
        if name not in MODES:
            raise ValueError(f"--priors must be one of {', '.join(MODES)}, got {name!r}")
        return cls.real() if name == "real" else cls()

    @property
    def exact(self) -> bool:
        return self.mode == "exact"

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def frame_affine(self, frame: int, seed: int) -> tuple[float, float]:
        """(s_n, c_n) of frame `frame`: scale and shift (in median inverse depths)."""
        rng = np.random.default_rng([seed, 0xD15, frame])
        lo, hi = self.scale_range
        s = math.exp(rng.uniform(math.log(lo), math.log(hi))) if hi > lo else lo
        a, b = self.shift_range
        return s, (rng.uniform(a, b) if b > a else a)

    def disparity(self, depth: np.ndarray, frame: int, seed: int) -> np.ndarray:
        """[H, W] float32 disparity of a frame whose metric z-depth is `depth` [H, W] (> 0)."""
        inverse = 1.0 / np.asarray(depth, np.float64)
        if self.exact:
            return inverse.astype(np.float32)
        if self.edge_blur_px > 0:
            inverse = cv2.GaussianBlur(inverse, (0, 0), self.edge_blur_px, borderType=cv2.BORDER_REFLECT)
        if self.bias > 0:
            inverse = inverse * np.exp(self.bias * self._field(inverse.shape, frame, seed))
        s, c = self.frame_affine(frame, seed)
        return (s * inverse / np.median(inverse) + s * c).astype(np.float32)

    def _field(self, shape: tuple[int, int], frame: int, seed: int) -> np.ndarray:
        """[H, W] smooth random field, unit standard deviation at the control points."""
        cells = int(self.bias_cells) + 1
        rng = np.random.default_rng([seed, 0xB1A5, frame])
        coarse = rng.standard_normal((cells, cells))
        return cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


__all__ = ["MODES", "Priors"]
