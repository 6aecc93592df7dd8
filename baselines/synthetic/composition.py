"""Scene-composition effects: they add or alter objects once, before rendering.

Each effect's ``expand(objects, rng)`` returns the new object tuple; it runs only for scenes that
list the effect. Random placement draws from ``rng``, which the simulator derives from the scene
seed, so a seed fixes the layout.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar, Optional

import numpy as np

from ._validate import (check_choice, check_color, check_float, check_int, check_name,
                        check_nonnegative, check_positive, check_vec3)
from .motion import NonRigid, RigidMotion
from .objects import SceneObject
from .textures import Texture


def _color(rng: np.random.Generator, low: float, high: float) -> tuple:
    return tuple(float(c) for c in rng.uniform(low, high, size=3))


@dataclass(frozen=True)
class ThinStructures:
    """Thin ribbons hanging from ``anchor`` that sway (non-rigid shear), plus optional thin
    static poles (effect ``thin_structures``). Ribbons are two-sided quads ``width`` wide."""

    effect: ClassVar[str] = "thin_structures"
    anchor: tuple = (0.0, 2.0, -0.5)
    spread: float = 1.2
    ribbons: int = 3
    length: float = 0.9
    width: float = 0.06
    sway: float = 0.3
    poles: int = 0
    pole_radius: float = 0.025

    def __post_init__(self) -> None:
        object.__setattr__(self, "anchor", check_vec3("ThinStructures.anchor", self.anchor))
        object.__setattr__(self, "spread", check_nonnegative("ThinStructures.spread", self.spread))
        check_int("ThinStructures.ribbons", self.ribbons, 0)
        check_int("ThinStructures.poles", self.poles, 0)
        if self.ribbons + self.poles == 0:
            raise ValueError("ThinStructures needs at least one ribbon or pole")
        for name in ("length", "width", "pole_radius"):
            object.__setattr__(self, name, check_positive(f"ThinStructures.{name}",
                                                          getattr(self, name)))
        object.__setattr__(self, "sway", check_nonnegative("ThinStructures.sway", self.sway))

    def expand(self, objects: tuple, rng: np.random.Generator) -> tuple:
        ax, ay, az = self.anchor
        added = []
        for i in range(self.ribbons):
            across = (i / (self.ribbons - 1) - 0.5) if self.ribbons > 1 else 0.0
            x = ax + self.spread * across + rng.uniform(-0.05, 0.05)
            z = az + rng.uniform(-0.15, 0.15)
            half = self.length / 2.0
            hue = _color(rng, 0.1, 0.9)
            texture = Texture("stripes", (hue, tuple(0.5 * c for c in hue)), period=0.12,
                              detail=0.3, axis=1)
            deform = None
            if self.sway > 0.0:
                deform = NonRigid(shear=self.sway, shear_axes="xy", shear_anchor=half,
                                  shear_cycles=float(rng.uniform(1.5, 3.0)),
                                  shear_phase_deg=float(rng.uniform(0.0, 360.0)))
            added.append(SceneObject(
                name=f"ribbon{i}", shape="quad", size=(self.width / 2.0, half, 1.0),
                position=(x, ay - half, z), rotation_deg=(0.0, float(rng.uniform(-35, 35)), 0.0),
                texture=texture, deform=deform))
        for i in range(self.poles):
            x = ax + self.spread * float(rng.uniform(-0.6, 0.6))
            z = az + float(rng.uniform(-0.3, 0.3))
            added.append(SceneObject(
                name=f"pole{i}", shape="cylinder", size=(self.pole_radius, ay / 2.0,
                                                         self.pole_radius),
                position=(x, ay / 2.0, z),
                texture=Texture("stripes", ((0.9, 0.9, 0.85), (0.7, 0.15, 0.1)), period=0.15,
                                axis=1)))
        return tuple(objects) + tuple(added)


@dataclass(frozen=True)
class FastObjects:
    """Small balls darting back and forth fast (effect ``fast_objects``).

    Each ball sits at a random point of the box ``center +- spread`` and oscillates with
    amplitude ``amplitude`` along a random direction, ``cycles`` times per sequence (+-20 %),
    spinning as it goes; its peak speed is 2 pi amplitude cycles scene units per sequence.
    """

    effect: ClassVar[str] = "fast_objects"
    count: int = 2
    radius: float = 0.08
    center: tuple = (0.0, 1.0, 0.0)
    spread: tuple = (1.0, 0.4, 0.5)
    amplitude: float = 0.8
    cycles: float = 3.0

    def __post_init__(self) -> None:
        check_int("FastObjects.count", self.count, 1)
        object.__setattr__(self, "radius", check_positive("FastObjects.radius", self.radius))
        object.__setattr__(self, "center", check_vec3("FastObjects.center", self.center))
        spread = check_vec3("FastObjects.spread", self.spread)
        if min(spread) < 0.0:
            raise ValueError(f"FastObjects.spread must be >= 0 per axis, got {spread}")
        object.__setattr__(self, "spread", spread)
        object.__setattr__(self, "amplitude",
                           check_positive("FastObjects.amplitude", self.amplitude))
        object.__setattr__(self, "cycles", check_positive("FastObjects.cycles", self.cycles))

    def expand(self, objects: tuple, rng: np.random.Generator) -> tuple:
        added = []
        for i in range(self.count):
            position = np.asarray(self.center) + rng.uniform(-1.0, 1.0, 3) * self.spread
            heading = rng.uniform(0.0, 2.0 * math.pi)
            direction = np.array([math.cos(heading), rng.uniform(-0.3, 0.3), math.sin(heading)])
            direction /= np.linalg.norm(direction)
            motion = RigidMotion(oscillation=tuple(float(v) for v in direction * self.amplitude),
                                 oscillation_cycles=self.cycles * float(rng.uniform(0.8, 1.2)),
                                 oscillation_phase_deg=float(rng.uniform(0.0, 360.0)),
                                 spin_axis=tuple(float(v) for v in rng.normal(size=3) + 1e-3),
                                 spin_deg=720.0)
            texture = Texture("checker", (_color(rng, 0.6, 1.0), _color(rng, 0.0, 0.4)),
                              period=self.radius * 0.7, detail=0.3)
            added.append(SceneObject(name=f"fast{i}", shape="sphere", size=(self.radius,) * 3,
                                     position=tuple(float(v) for v in position),
                                     texture=texture, motion=motion))
        return tuple(objects) + tuple(added)


@dataclass(frozen=True)
class Occlusion:
    """An occluder (``box`` or ``cylinder`` with half extents ``size``) at ``position``,
    travelling by ``travel`` over the sequence; place it between the camera and the action
    (effect ``occlusion``)."""

    effect: ClassVar[str] = "occlusion"
    position: tuple = (0.0, 0.9, 1.0)
    size: tuple = (0.12, 0.9, 0.12)
    travel: tuple = (0.0, 0.0, 0.0)
    shape: str = "box"

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", check_vec3("Occlusion.position", self.position))
        size = check_vec3("Occlusion.size", self.size)
        if min(size) <= 0.0:
            raise ValueError(f"Occlusion.size must be positive per axis, got {size}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "travel", check_vec3("Occlusion.travel", self.travel))
        check_choice("Occlusion.shape", self.shape, ("box", "cylinder"))

    def expand(self, objects: tuple, rng: np.random.Generator) -> tuple:
        motion = RigidMotion(velocity=self.travel) if any(self.travel) else None
        texture = Texture("noise", (_color(rng, 0.5, 0.9), _color(rng, 0.05, 0.35)),
                          period=0.15, detail=0.4)
        occluder = SceneObject(name="occluder", shape=self.shape, size=self.size,
                               position=self.position, texture=texture, motion=motion)
        return tuple(objects) + (occluder,)


@dataclass(frozen=True)
class Textureless:
    """Deliberately textureless surfaces (effect ``textureless``): the named objects get a flat
    colour (their texture's first colour), and optionally a flat panel (a quad with half
    extents ``panel_size`` facing +z, rotated ``panel_yaw_deg`` about world up) is added at
    ``panel``."""

    effect: ClassVar[str] = "textureless"
    objects: tuple = ()
    panel: Optional[tuple] = None
    panel_size: tuple = (1.0, 0.8, 1.0)
    panel_yaw_deg: float = 0.0
    panel_color: tuple = (0.55, 0.6, 0.65)

    def __post_init__(self) -> None:
        if not isinstance(self.objects, (tuple, list)):
            raise ValueError(f"Textureless.objects must be a list of object names, "
                             f"got {self.objects!r}")
        object.__setattr__(self, "objects", tuple(check_name(f"Textureless.objects[{i}]", n)
                                                  for i, n in enumerate(self.objects)))
        if self.panel is not None:
            object.__setattr__(self, "panel", check_vec3("Textureless.panel", self.panel))
        elif not self.objects:
            raise ValueError("Textureless needs object names and/or a panel")
        size = check_vec3("Textureless.panel_size", self.panel_size)
        if min(size) <= 0.0:
            raise ValueError(f"Textureless.panel_size must be positive per axis, got {size}")
        object.__setattr__(self, "panel_size", size)
        object.__setattr__(self, "panel_yaw_deg",
                           check_float("Textureless.panel_yaw_deg", self.panel_yaw_deg))
        object.__setattr__(self, "panel_color",
                           check_color("Textureless.panel_color", self.panel_color))

    def expand(self, objects: tuple, rng: np.random.Generator) -> tuple:
        names = {obj.name for obj in objects}
        for name in self.objects:
            if name not in names:
                raise ValueError(f"Textureless.objects names unknown object {name!r}; "
                                 f"known: {', '.join(sorted(names))}")
        out = tuple(replace(obj, texture=Texture("flat", obj.texture.colors))
                    if obj.name in self.objects else obj for obj in objects)
        if self.panel is not None:
            out += (SceneObject(name="textureless_panel", shape="quad", size=self.panel_size,
                                position=self.panel, rotation_deg=(0.0, self.panel_yaw_deg, 0.0),
                                texture=Texture("flat", (self.panel_color, self.panel_color))),)
        return out
