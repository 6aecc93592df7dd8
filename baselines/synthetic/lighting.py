"""Shading: one directional light plus ambient (Lambertian), and the global lighting-change effect."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional

import numpy as np

from ._validate import check_direction, check_float, check_nonnegative, check_positive
from .transforms import WORLD_UP, rotation_axis_angle


@dataclass(frozen=True)
class Light:
    """Directional light (``direction`` points from surfaces towards the light) plus ambient.

    Shading is ``albedo * (ambient + diffuse * max(0, n . l)) * gain`` with two-sided normals,
    view-independent, so a static surface keeps its colour under camera motion.
    """

    direction: tuple = (0.4, 1.0, 0.7)
    ambient: float = 0.5
    diffuse: float = 0.5

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction", check_direction("Light.direction", self.direction))
        object.__setattr__(self, "ambient", check_nonnegative("Light.ambient", self.ambient))
        object.__setattr__(self, "diffuse", check_nonnegative("Light.diffuse", self.diffuse))


@dataclass(frozen=True)
class LightingChange:
    """Global lighting change over time (effect ``lighting``).

    The light's intensity goes linearly from ``gain_start`` to ``gain_end``, times a flicker
    ``1 + flicker * sin(2 pi flicker_cycles t)``, and its direction turns by ``sweep_deg`` about
    world up over the sequence. Brightness changes break brightness constancy on purpose.
    """

    effect: ClassVar[str] = "lighting"
    gain_start: float = 1.0
    gain_end: float = 0.6
    flicker: float = 0.0
    flicker_cycles: float = 3.0
    sweep_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("gain_start", "gain_end"):
            object.__setattr__(self, name, check_positive(f"LightingChange.{name}",
                                                          getattr(self, name)))
        flicker = check_nonnegative("LightingChange.flicker", self.flicker)
        if flicker >= 1.0:
            raise ValueError(f"LightingChange.flicker must be < 1, got {flicker!r}")
        object.__setattr__(self, "flicker", flicker)
        object.__setattr__(self, "flicker_cycles",
                           check_nonnegative("LightingChange.flicker_cycles", self.flicker_cycles))
        object.__setattr__(self, "sweep_deg",
                           check_float("LightingChange.sweep_deg", self.sweep_deg))

    def gain(self, t: float) -> float:
        """Intensity factor at time ``t``."""
        ramp = self.gain_start + (self.gain_end - self.gain_start) * t
        return ramp * (1.0 + self.flicker * math.sin(2.0 * math.pi * self.flicker_cycles * t))

    def direction(self, base: np.ndarray, t: float) -> np.ndarray:
        """Light direction [3] at time ``t`` given the base direction."""
        return rotation_axis_angle(WORLD_UP, self.sweep_deg * t)[:3, :3] @ base


@dataclass(frozen=True)
class LightState:
    """The light at one instant: unit direction [3] and intensity gain."""

    direction: np.ndarray
    ambient: float
    diffuse: float
    gain: float

    def shade(self, albedo: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Lambertian colour for albedo [M,3] and unit normals [M,3] facing the viewer -> [M,3]."""
        lambert = np.clip(normals @ self.direction, 0.0, None)
        return albedo * ((self.ambient + self.diffuse * lambert) * self.gain)[:, None]


def light_at(light: Light, change: Optional[LightingChange], t: float) -> LightState:
    """The light at time ``t``; ``change`` is None for scenes without the lighting effect."""
    direction = np.asarray(light.direction) / np.linalg.norm(light.direction)
    gain = 1.0
    if change is not None:
        direction = change.direction(direction, t)
        gain = change.gain(t)
    return LightState(direction=direction, ambient=light.ambient, diffuse=light.diffuse, gain=gain)
