"""A built scene: expanded objects resolved into a hierarchy, evaluated at any time t.

``BuiltScene.placements(t)`` gives every renderable object's unit-shape -> world matrix at time
``t`` (also for objects absent at ``t``: ground-truth flow still needs to know where a vanished
surface point would be) with its presence flag and a world bounding sphere for culling.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .objects import SceneObject
from .shapes import RENDERABLE_SHAPES
from .spec import SceneSpec
from .textures import texture_seed
from .transforms import rotation_euler, scaling, translation

# Radius of the sphere around the origin that contains each unit shape.
_UNIT_BOUND = {"sphere": 1.0, "box": 3.0 ** 0.5, "room": 3.0 ** 0.5, "cylinder": 2.0 ** 0.5,
               "quad": 2.0 ** 0.5}


@dataclass(frozen=True)
class Placement:
    """One renderable object at one instant.

    Attributes:
        index: index of the object in ``BuiltScene.objects``.
        shape: its unit shape.
        to_world: [4,4] unit-shape -> world (affine).
        to_local: [4,4] inverse of ``to_world``.
        present: whether the object exists at this instant.
        center, radius: world bounding sphere ([3], float); radius is inf for rooms (no culling).
    """

    index: int
    shape: str
    to_world: np.ndarray
    to_local: np.ndarray
    present: bool
    center: np.ndarray
    radius: float


class BuiltScene:
    """Objects of a spec after composition effects, with parents resolved and dynamics known."""

    def __init__(self, spec: SceneSpec):
        self.spec = spec
        self.objects: tuple[SceneObject, ...] = spec.expanded_objects()
        names = [obj.name for obj in self.objects]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"scene {spec.name!r}: duplicate object names {duplicates}")
        by_name = {name: i for i, name in enumerate(names)}
        self.parent = [-1] * len(self.objects)
        for i, obj in enumerate(self.objects):
            if obj.attach is not None:
                if obj.attach.parent not in by_name:
                    raise ValueError(f"scene {spec.name!r}: object {obj.name!r} is attached to "
                                     f"unknown parent {obj.attach.parent!r}")
                self.parent[i] = by_name[obj.attach.parent]
        self.order = self._topological_order()
        self.dynamic = np.zeros(len(self.objects), dtype=bool)
        for i in self.order:  # parents first, so dynamics propagate down the hierarchy
            obj = self.objects[i]
            own = obj.motion is not None or obj.deform is not None or obj.visibility is not None
            self.dynamic[i] = own or (self.parent[i] >= 0 and self.dynamic[self.parent[i]])
        self.renderable = [i for i, obj in enumerate(self.objects) if obj.shape in RENDERABLE_SHAPES]
        if not self.renderable:
            raise ValueError(f"scene {spec.name!r} has no renderable object (only groups)")
        self.texture_seeds = [texture_seed(spec.seed, i) for i in range(len(self.objects))]

    def _topological_order(self) -> list[int]:
        order, state = [], [0] * len(self.objects)  # 0 new, 1 visiting, 2 done

        def visit(i: int) -> None:
            if state[i] == 2:
                return
            if state[i] == 1:
                raise ValueError(f"scene {self.spec.name!r}: attachment cycle through object "
                                 f"{self.objects[i].name!r}")
            state[i] = 1
            if self.parent[i] >= 0:
                visit(self.parent[i])
            state[i] = 2
            order.append(i)

        for i in range(len(self.objects)):
            visit(i)
        return order

    @property
    def dynamic_names(self) -> list[str]:
        return [obj.name for obj, dyn in zip(self.objects, self.dynamic) if dyn]

    def placements(self, t: float) -> list[Placement]:
        """Every renderable object at time ``t`` (present or not), ordered by object index."""
        poses: dict[int, np.ndarray] = {}
        present: dict[int, bool] = {}
        for i in self.order:
            obj = self.objects[i]
            pose = translation(obj.position) @ rotation_euler(obj.rotation_deg)
            if obj.motion is not None:
                pose = pose @ obj.motion.matrix(t)
            alive = obj.visibility.present(t) if obj.visibility is not None else True
            if obj.attach is not None:
                parent = self.parent[i]
                pose = obj.attach.compose(poses[parent], pose)
                alive = alive and present[parent]
            poses[i], present[i] = pose, alive
        out = []
        for i in self.renderable:
            obj = self.objects[i]
            shape_matrix = scaling(obj.size)
            if obj.deform is not None:
                shape_matrix = obj.deform.matrix(t) @ shape_matrix
            to_world = poses[i] @ shape_matrix
            to_local = np.linalg.inv(to_world)
            stretch = float(np.linalg.norm(to_world[:3, :3], ord=2))
            radius = np.inf if obj.shape == "room" else _UNIT_BOUND[obj.shape] * stretch
            out.append(Placement(index=i, shape=obj.shape, to_world=to_world, to_local=to_local,
                                 present=present[i], center=to_world[:3, 3].copy(), radius=radius))
        return out
