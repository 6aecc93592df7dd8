"""Scene objects: a unit shape with a size, a rest pose, a texture and optional per-object effects."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from ._validate import check_choice, check_name, check_vec3
from .motion import Attachment, NonRigid, RigidMotion, Visibility
from .shapes import SHAPES
from .textures import Texture

# Per-object effect slots: attribute name -> effect class.
OBJECT_EFFECT_SLOTS = {"attach": Attachment, "motion": RigidMotion, "deform": NonRigid,
                       "visibility": Visibility}


@dataclass(frozen=True)
class SceneObject:
    """One object of a scene.

    Its world matrix at time t is

        parent_pose(t) @ T(position) @ R(rotation_deg) @ motion(t)  @  deform(t) @ S(size)
        '-------------------- pose(t): carried by children --------'  '-- shape only --'

    where the unit shape (see ``shapes``) is scaled per axis by ``size`` (radii / half extents)
    and the texture is evaluated at unit-shape coordinates times ``size``.

    Attributes:
        name: unique within the scene.
        shape: ``sphere``, ``box``, ``room``, ``cylinder``, ``quad`` or ``group`` (no geometry).
        size: per-axis half extents of the unit shape, scene units.
        position, rotation_deg: rest pose (extrinsic x, y, z Euler angles) relative to the
            parent, or to the world without one.
        texture: surface texture (ignored for ``group``).
        attach: ``Attachment`` to a parent object (articulated hierarchy), or None.
        motion: ``RigidMotion`` or None.
        deform: ``NonRigid`` deformation or None.
        visibility: ``Visibility`` window (appearing / disappearing object) or None.
    """

    name: str
    shape: str
    size: tuple = (1.0, 1.0, 1.0)
    position: tuple = (0.0, 0.0, 0.0)
    rotation_deg: tuple = (0.0, 0.0, 0.0)
    texture: Texture = field(default_factory=Texture)
    attach: Optional[Attachment] = None
    motion: Optional[RigidMotion] = None
    deform: Optional[NonRigid] = None
    visibility: Optional[Visibility] = None

    def __post_init__(self) -> None:
        check_name("SceneObject.name", self.name)
        where = f"object {self.name!r}"
        check_choice(f"{where}: shape", self.shape, SHAPES)
        size = check_vec3(f"{where}: size", self.size)
        if min(size) <= 0.0:
            raise ValueError(f"{where}: size must be positive per axis, got {size}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "position", check_vec3(f"{where}: position", self.position))
        object.__setattr__(self, "rotation_deg",
                           check_vec3(f"{where}: rotation_deg", self.rotation_deg))
        if not isinstance(self.texture, Texture):
            raise ValueError(f"{where}: texture must be a Texture, got {type(self.texture).__name__}")
        for slot, cls in OBJECT_EFFECT_SLOTS.items():
            value = getattr(self, slot)
            if value is not None and not isinstance(value, cls):
                raise ValueError(f"{where}: {slot} must be a {cls.__name__} or None, "
                                 f"got {type(value).__name__}")
        if self.shape == "group" and self.deform is not None:
            raise ValueError(f"{where}: a group has no shape to deform")

    @property
    def effects(self) -> tuple[str, ...]:
        """Names of the per-object effects this object uses."""
        return tuple(cls.effect for slot, cls in OBJECT_EFFECT_SLOTS.items()
                     if getattr(self, slot) is not None)

    @property
    def renderable(self) -> bool:
        return self.shape != "group"
