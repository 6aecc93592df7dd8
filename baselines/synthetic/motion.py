"""Per-object effects: rigid motion, articulation, non-rigid deformation, appearance.

All motions are functions of the sequence time t in [0, 1], so a scene keeps its choreography
when rendered with more or fewer frames. Every effect maps to a 4x4 affine matrix (or a
presence flag), which keeps the ray casting and the ground-truth flow exact.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional

import numpy as np

from ._validate import (check_direction, check_float, check_name, check_nonnegative,
                        check_range, check_vec3)
from .transforms import rotation_axis_angle, translation


@dataclass(frozen=True)
class RigidMotion:
    """Rigid motion of an object relative to its rest pose (effect ``rigid``).

    translation(t) = velocity * t + oscillation * sin(2 pi (oscillation_cycles t) + phase)
    rotation(t)    = spin about spin_axis by spin_deg * t, then a pendulum swing about swing_axis
                     of amplitude swing_deg: swing_deg * sin(2 pi swing_cycles t + phase)
    Rotations act about the object's origin (its ``position``), so a ``group`` object swinging
    carries its children like a pendulum. Units: scene units and degrees per whole sequence.
    """

    effect: ClassVar[str] = "rigid"
    velocity: tuple = (0.0, 0.0, 0.0)
    oscillation: tuple = (0.0, 0.0, 0.0)
    oscillation_cycles: float = 1.0
    oscillation_phase_deg: float = 0.0
    spin_axis: tuple = (0.0, 1.0, 0.0)
    spin_deg: float = 0.0
    swing_axis: tuple = (0.0, 0.0, 1.0)
    swing_deg: float = 0.0
    swing_cycles: float = 1.0
    swing_phase_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("velocity", "oscillation"):
            object.__setattr__(self, name, check_vec3(f"RigidMotion.{name}", getattr(self, name)))
        for name in ("spin_axis", "swing_axis"):
            object.__setattr__(self, name,
                               check_direction(f"RigidMotion.{name}", getattr(self, name)))
        for name in ("oscillation_cycles", "swing_cycles"):
            object.__setattr__(self, name,
                               check_nonnegative(f"RigidMotion.{name}", getattr(self, name)))
        for name in ("oscillation_phase_deg", "spin_deg", "swing_deg", "swing_phase_deg"):
            object.__setattr__(self, name, check_float(f"RigidMotion.{name}", getattr(self, name)))

    def matrix(self, t: float) -> np.ndarray:
        """[4,4] rigid transform at time ``t`` (applied in the object's rest frame)."""
        wave = math.sin(2.0 * math.pi * self.oscillation_cycles * t
                        + math.radians(self.oscillation_phase_deg))
        offset = np.asarray(self.velocity) * t + np.asarray(self.oscillation) * wave
        swing = self.swing_deg * math.sin(2.0 * math.pi * self.swing_cycles * t
                                          + math.radians(self.swing_phase_deg))
        return (translation(offset) @ rotation_axis_angle(self.spin_axis, self.spin_deg * t)
                @ rotation_axis_angle(self.swing_axis, swing))


@dataclass(frozen=True)
class NonRigid:
    """Time-varying affine deformation of an object's shape (effect ``nonrigid``).

    Acts in the object's own metric frame (after sizing, before the pose): per-axis scale
    factors eased (smoothstep) from ``scale_start`` to ``scale_end``, then a shear
    ``u += k(t) (v - s_v shear_anchor)`` with ``k(t) = shear * sin(2 pi shear_cycles t + phase)``,
    where ``shear_axes`` = "uv" names the moved axis u and the lever axis v, and ``shear_anchor``
    is the rest-frame v coordinate (scene units) of the line that stays put (e.g. "xy" with
    anchor = half the length: a hanging ribbon swaying about its top edge). Affine maps keep the
    shape exactly ray-castable; true bending is approximated by shear.
    """

    effect: ClassVar[str] = "nonrigid"
    scale_start: tuple = (1.0, 1.0, 1.0)
    scale_end: tuple = (1.0, 1.0, 1.0)
    shear: float = 0.0
    shear_axes: str = "xy"
    shear_anchor: float = 0.0
    shear_cycles: float = 1.0
    shear_phase_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("scale_start", "scale_end"):
            vec = check_vec3(f"NonRigid.{name}", getattr(self, name))
            if min(vec) <= 0.0:
                raise ValueError(f"NonRigid.{name} must be positive per axis, got {vec}")
            object.__setattr__(self, name, vec)
        if (not isinstance(self.shear_axes, str) or len(self.shear_axes) != 2
                or any(a not in "xyz" for a in self.shear_axes)
                or self.shear_axes[0] == self.shear_axes[1]):
            raise ValueError(f"NonRigid.shear_axes must be two different letters of 'xyz', "
                             f"got {self.shear_axes!r}")
        object.__setattr__(self, "shear", check_float("NonRigid.shear", self.shear))
        object.__setattr__(self, "shear_anchor",
                           check_float("NonRigid.shear_anchor", self.shear_anchor))
        object.__setattr__(self, "shear_cycles",
                           check_nonnegative("NonRigid.shear_cycles", self.shear_cycles))
        object.__setattr__(self, "shear_phase_deg",
                           check_float("NonRigid.shear_phase_deg", self.shear_phase_deg))

    def matrix(self, t: float) -> np.ndarray:
        """[4,4] affine deformation at time ``t`` (object frame, scene units)."""
        ease = t * t * (3.0 - 2.0 * t)
        scale = np.asarray(self.scale_start) + (np.asarray(self.scale_end)
                                                - np.asarray(self.scale_start)) * ease
        k = self.shear * math.sin(2.0 * math.pi * self.shear_cycles * t
                                  + math.radians(self.shear_phase_deg))
        u, v = ("xyz".index(a) for a in self.shear_axes)
        shear = np.eye(4)
        shear[u, v] = k
        shear[u, 3] = -k * self.shear_anchor * scale[v]  # keep the anchor line in place
        return shear @ np.diag([*scale, 1.0])


@dataclass(frozen=True)
class Attachment:
    """Hierarchical transform: the object's pose is relative to ``parent``'s pose (effect
    ``articulated``); it inherits the parent's rigid motion and presence, not its size or
    deformation."""

    effect: ClassVar[str] = "articulated"
    parent: str = ""

    def __post_init__(self) -> None:
        check_name("Attachment.parent", self.parent)

    def compose(self, parent_pose: np.ndarray, local_pose: np.ndarray) -> np.ndarray:
        """World pose [4,4] of the child from the parent's world pose and its own local pose."""
        return parent_pose @ local_pose


@dataclass(frozen=True)
class Visibility:
    """The object exists only for ``appear <= t < disappear`` (effect ``appearance``); None
    means from the start / to the end."""

    effect: ClassVar[str] = "appearance"
    appear: Optional[float] = None
    disappear: Optional[float] = None

    def __post_init__(self) -> None:
        if self.appear is not None:
            object.__setattr__(self, "appear", check_range("Visibility.appear", self.appear, 0, 1))
        if self.disappear is not None:
            object.__setattr__(self, "disappear",
                               check_range("Visibility.disappear", self.disappear, 0, 1))
        if self.appear is None and self.disappear is None:
            raise ValueError("Visibility needs appear and/or disappear")
        if (self.appear is not None and self.disappear is not None
                and self.appear >= self.disappear):
            raise ValueError(f"Visibility.appear ({self.appear}) must be < Visibility.disappear "
                             f"({self.disappear})")

    def present(self, t: float) -> bool:
        """Whether the object exists at time ``t``."""
        if self.appear is not None and t < self.appear:
            return False
        return not (self.disappear is not None and t >= self.disappear)
