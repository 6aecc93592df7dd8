"""Camera paths and camera effects.

A path gives, for frame ``i`` at time ``t = i / (N - 1)``, the camera-to-world pose (OpenCV axes)
and the id of the physical camera that took the frame. ``StaticCamera`` is the effect-free
default; ``Pan``, ``Orbit``, ``Forward`` and ``Rig`` are effects named after their ``effect``
attribute. ``Shake`` (hand-held jitter on top of any path) and ``Vrig`` (a second camera at a
fixed offset, HyperNeRF's validation rig) are scene-level effects. Code of an effect only runs
when a scene lists it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional, Union

import numpy as np

from ._validate import (check_float, check_int, check_nonnegative, check_positive, check_vec3)
from .transforms import WORLD_UP, look_at, rotation_axis_angle, rotation_vector, translation


def _check_view(owner: str, eye: tuple, target: tuple) -> None:
    forward = np.subtract(target, eye)
    norm = np.linalg.norm(forward)
    if norm < 1e-9:
        raise ValueError(f"{owner}: look_at coincides with the camera position {eye}")
    if np.linalg.norm(np.cross(forward / norm, WORLD_UP)) < 1e-6:
        raise ValueError(f"{owner}: the camera looks straight up or down (position {eye}, "
                         f"look_at {target}); tilt it")


@dataclass(frozen=True)
class StaticCamera:
    """One camera that never moves (no effect)."""

    effect: ClassVar[Optional[str]] = None
    position: tuple = (0.0, 1.4, 3.5)
    look_at: tuple = (0.0, 1.0, -1.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", check_vec3("StaticCamera.position", self.position))
        object.__setattr__(self, "look_at", check_vec3("StaticCamera.look_at", self.look_at))
        _check_view("StaticCamera", self.position, self.look_at)

    @property
    def camera_count(self) -> int:
        return 1

    def pose(self, frame: int, t: float) -> tuple[np.ndarray, int]:
        return look_at(self.position, self.look_at), 0


@dataclass(frozen=True)
class Pan:
    """Pure rotation about the camera centre: the view turns about world up by ``sweep_deg``
    over the sequence, centred on ``look_at`` (effect ``pan``)."""

    effect: ClassVar[Optional[str]] = "pan"
    position: tuple = (0.0, 1.4, 3.5)
    look_at: tuple = (0.0, 1.0, -1.0)
    sweep_deg: float = 20.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", check_vec3("Pan.position", self.position))
        object.__setattr__(self, "look_at", check_vec3("Pan.look_at", self.look_at))
        object.__setattr__(self, "sweep_deg", check_float("Pan.sweep_deg", self.sweep_deg))
        _check_view("Pan", self.position, self.look_at)

    @property
    def camera_count(self) -> int:
        return 1

    def pose(self, frame: int, t: float) -> tuple[np.ndarray, int]:
        c2w = look_at(self.position, self.look_at)
        yaw = rotation_axis_angle(WORLD_UP, self.sweep_deg * (t - 0.5))
        c2w[:3, :3] = yaw[:3, :3] @ c2w[:3, :3]
        return c2w, 0


@dataclass(frozen=True)
class Orbit:
    """Camera on a horizontal arc around ``target``, always looking at it (effect ``orbit``).

    Angle ``start_deg + sweep_deg * t`` is measured about world up from the +z axis.
    """

    effect: ClassVar[Optional[str]] = "orbit"
    target: tuple = (0.0, 1.0, -1.0)
    radius: float = 4.5
    height: float = 0.4
    start_deg: float = -15.0
    sweep_deg: float = 30.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "target", check_vec3("Orbit.target", self.target))
        object.__setattr__(self, "radius", check_positive("Orbit.radius", self.radius))
        object.__setattr__(self, "height", check_float("Orbit.height", self.height))
        object.__setattr__(self, "start_deg", check_float("Orbit.start_deg", self.start_deg))
        object.__setattr__(self, "sweep_deg", check_float("Orbit.sweep_deg", self.sweep_deg))
        _check_view("Orbit", self._eye(0.0), self.target)

    @property
    def camera_count(self) -> int:
        return 1

    def _eye(self, t: float) -> tuple:
        angle = math.radians(self.start_deg + self.sweep_deg * t)
        tx, ty, tz = self.target
        return (tx + self.radius * math.sin(angle), ty + self.height,
                tz + self.radius * math.cos(angle))

    def pose(self, frame: int, t: float) -> tuple[np.ndarray, int]:
        return look_at(self._eye(t), self.target), 0


@dataclass(frozen=True)
class Forward:
    """Camera moving ``distance`` along its (fixed) view direction over the sequence
    (effect ``forward``)."""

    effect: ClassVar[Optional[str]] = "forward"
    position: tuple = (0.0, 1.4, 3.5)
    look_at: tuple = (0.0, 1.0, -1.0)
    distance: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", check_vec3("Forward.position", self.position))
        object.__setattr__(self, "look_at", check_vec3("Forward.look_at", self.look_at))
        object.__setattr__(self, "distance", check_float("Forward.distance", self.distance))
        _check_view("Forward", self.position, self.look_at)

    @property
    def camera_count(self) -> int:
        return 1

    def pose(self, frame: int, t: float) -> tuple[np.ndarray, int]:
        c2w = look_at(self.position, self.look_at)
        c2w[:3, 3] += c2w[:3, 2] * self.distance * t
        return c2w, 0


@dataclass(frozen=True)
class Rig:
    """``count`` fixed cameras; frame ``i`` is seen from camera ``i % count`` (effect ``rig``).

    This is how the NVIDIA monocular protocol builds a "monocular" video from a camera array,
    so consecutive frames jump between viewpoints. The cameras sit on ``rows`` horizontal rows
    of total width ``baseline``, centred on ``position`` (rows ``row_spacing`` apart) and all
    look at ``look_at``; ids run left to right, top row first.
    """

    effect: ClassVar[Optional[str]] = "rig"
    position: tuple = (0.0, 1.4, 3.5)
    look_at: tuple = (0.0, 1.0, -1.0)
    count: int = 12
    baseline: float = 1.0
    rows: int = 2
    row_spacing: float = 0.25

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", check_vec3("Rig.position", self.position))
        object.__setattr__(self, "look_at", check_vec3("Rig.look_at", self.look_at))
        check_int("Rig.count", self.count, 1)
        check_int("Rig.rows", self.rows, 1)
        if self.rows > self.count:
            raise ValueError(f"Rig.rows ({self.rows}) must not exceed Rig.count ({self.count})")
        object.__setattr__(self, "baseline", check_nonnegative("Rig.baseline", self.baseline))
        object.__setattr__(self, "row_spacing",
                           check_nonnegative("Rig.row_spacing", self.row_spacing))
        _check_view("Rig", self.position, self.look_at)

    @property
    def camera_count(self) -> int:
        return self.count

    def camera_position(self, camera_id: int) -> np.ndarray:
        """World position [3] of rig camera ``camera_id``."""
        per_row = math.ceil(self.count / self.rows)
        row, col = divmod(camera_id, per_row)
        centre = look_at(self.position, self.look_at)
        right = centre[:3, 0]
        across = col / (per_row - 1) - 0.5 if per_row > 1 else 0.0
        down = row - (self.rows - 1) / 2.0
        return (np.asarray(self.position) + right * across * self.baseline
                - WORLD_UP * down * self.row_spacing)

    def pose(self, frame: int, t: float) -> tuple[np.ndarray, int]:
        camera_id = frame % self.count
        return look_at(self.camera_position(camera_id), self.look_at), camera_id


CameraPath = Union[StaticCamera, Pan, Orbit, Forward, Rig]
CAMERA_PATHS: dict[str, type] = {"static": StaticCamera, "pan": Pan, "orbit": Orbit,
                                 "forward": Forward, "rig": Rig}


@dataclass(frozen=True)
class Shake:
    """Hand-held jitter added to the path in the camera's own frame (effect ``shake``).

    Each of the 3 rotation and 3 translation components is a smooth sum of three sinusoids
    (``cycles``, 1.7x and 2.9x as many cycles per sequence) with phases drawn from the scene seed;
    amplitudes are the peak values in degrees and scene units.
    """

    effect: ClassVar[str] = "shake"
    rotation_deg: float = 0.5
    translation: float = 0.03
    cycles: float = 2.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "rotation_deg",
                           check_nonnegative("Shake.rotation_deg", self.rotation_deg))
        object.__setattr__(self, "translation",
                           check_nonnegative("Shake.translation", self.translation))
        object.__setattr__(self, "cycles", check_positive("Shake.cycles", self.cycles))

    def perturb(self, c2w: np.ndarray, t: float, seed: int) -> np.ndarray:
        """Jittered copy of camera-to-world ``c2w`` [4,4] at time ``t``."""
        rng = np.random.default_rng([int(seed), 0x5AC3])
        phases = rng.uniform(0.0, 2.0 * np.pi, size=(6, 3))
        freqs = self.cycles * np.array([1.0, 1.7, 2.9])
        weights = np.array([1.0, 0.5, 0.25]) / 1.75
        signal = (weights * np.sin(2.0 * np.pi * freqs * t + phases)).sum(axis=1)  # [6] in [-1, 1]
        jitter = rotation_vector(np.radians(self.rotation_deg) * signal[:3])
        jitter[:3, 3] = self.translation * signal[3:]
        return c2w @ jitter


@dataclass(frozen=True)
class Vrig:
    """A second camera rigidly mounted at ``offset`` (camera frame, scene units) from the main one
    at every timestamp, as in HyperNeRF's validation rig: train on one, test on the other
    (effect ``vrig``)."""

    effect: ClassVar[str] = "vrig"
    offset: tuple = (0.3, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", check_vec3("Vrig.offset", self.offset))
        if max(abs(v) for v in self.offset) == 0.0:
            raise ValueError("Vrig.offset must be non-zero (the second camera would coincide)")

    def second_camera(self, c2w: np.ndarray) -> np.ndarray:
        """Camera-to-world [4,4] of the second camera given the main one's."""
        return c2w @ translation(self.offset)
