"""Scene specifications: a scene is a list of objects, a camera path and the effects it calls for.

``SceneSpec`` is a frozen dataclass; ``SceneSpec.from_dict`` / ``to_dict`` give the JSON form:

    {"name": "demo", "frames": 24, "width": 96, "height": 72, "seed": 0,
     "camera": {"path": "orbit", "radius": 4.0, "sweep_deg": 30},
     "objects": [{"name": "room", "shape": "room", "size": [4, 2, 4.5], "position": [0, 2, 0],
                  "texture": {"kind": "checker", "period": 0.5, "detail": 0.4}},
                 {"name": "ball", "shape": "sphere", "size": [0.3, 0.3, 0.3],
                  "position": [0, 1, 0], "motion": {"velocity": [1, 0, 0]}}],
     "effects": {"shake": {"rotation_deg": 0.5}}}

Effects come in three kinds, all listed in ``EFFECTS``: the camera path (``pan``, ``orbit``,
``forward``, ``rig``; a static camera is no effect), per-object slots (``rigid``, ``nonrigid``,
``articulated``, ``appearance``) and scene-level components (``shake``, ``vrig``, ``lighting``,
``thin_structures``, ``fast_objects``, ``occlusion``, ``textureless``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ._validate import check_int, check_name, check_range
from .camera import CAMERA_PATHS, CameraPath, Forward, Orbit, Pan, Rig, Shake, StaticCamera, Vrig
from .composition import FastObjects, Occlusion, Textureless, ThinStructures
from .lighting import Light, LightingChange
from .objects import OBJECT_EFFECT_SLOTS, SceneObject
from .textures import Texture

CAMERA_EFFECTS: dict[str, type] = {cls.effect: cls for cls in (Pan, Orbit, Forward, Rig)}
OBJECT_EFFECTS: dict[str, type] = {cls.effect: cls for cls in OBJECT_EFFECT_SLOTS.values()}
SCENE_EFFECTS: dict[str, type] = {cls.effect: cls for cls in (
    Shake, Vrig, LightingChange, ThinStructures, FastObjects, Occlusion, Textureless)}
# Every effect by name, in the order scene listings report them.
EFFECTS: dict[str, type] = {**CAMERA_EFFECTS, **OBJECT_EFFECTS, **SCENE_EFFECTS}
# Effects that add or alter objects before rendering (have ``expand``).
COMPOSITION_EFFECTS = (ThinStructures, FastObjects, Occlusion, Textureless)

_TOP_LEVEL_KEYS = ("name", "description", "frames", "width", "height", "fov_deg", "seed",
                   "supersample", "camera", "light", "objects", "effects")


@dataclass(frozen=True)
class SceneSpec:
    """A synthetic dynamic scene.

    Attributes:
        name: scene name (used in listings and scene.json).
        objects: the declared objects (composition effects may add more at build time).
        camera: camera path; ``StaticCamera`` means no camera effect.
        light: directional + ambient light.
        effects: scene-level effect components (at most one of each kind).
        frames: number of frames N >= 2; frame i is at time i / (N - 1).
        width, height: image size in pixels.
        fov_deg: horizontal field of view.
        seed: random seed (textures, shake, layout of composition effects).
        supersample: s, colour is averaged over s x s samples per pixel (anti-aliasing); depth,
            flow and masks are always taken at pixel centres.
        description: one line for ``--list``.
    """

    name: str
    objects: tuple
    camera: Any = field(default_factory=StaticCamera)
    light: Light = field(default_factory=Light)
    effects: tuple = ()
    frames: int = 32
    width: int = 128
    height: int = 96
    fov_deg: float = 60.0
    seed: int = 0
    supersample: int = 2
    description: str = ""

    def __post_init__(self) -> None:
        check_name("SceneSpec.name", self.name)
        check_int("frames", self.frames, 2)
        check_int("width", self.width, 1)
        check_int("height", self.height, 1)
        check_int("seed", self.seed, 0)
        check_int("supersample", self.supersample, 1)
        object.__setattr__(self, "fov_deg", check_range("fov_deg", self.fov_deg, 1.0, 170.0))
        if not isinstance(self.description, str):
            raise ValueError(f"description must be a string, got {self.description!r}")
        if not isinstance(self.camera, tuple(CAMERA_PATHS.values())):
            raise ValueError(f"camera must be one of {', '.join(c.__name__ for c in CAMERA_PATHS.values())}, "
                             f"got {type(self.camera).__name__}")
        if not isinstance(self.light, Light):
            raise ValueError(f"light must be a Light, got {type(self.light).__name__}")
        if not isinstance(self.objects, (tuple, list)) or not self.objects:
            raise ValueError(f"scene {self.name!r}: objects must be a non-empty list of SceneObject")
        object.__setattr__(self, "objects", tuple(self.objects))
        for obj in self.objects:
            if not isinstance(obj, SceneObject):
                raise ValueError(f"scene {self.name!r}: objects must be SceneObject, "
                                 f"got {type(obj).__name__}")
        if not isinstance(self.effects, (tuple, list)):
            raise ValueError(f"scene {self.name!r}: effects must be a list of effect components")
        object.__setattr__(self, "effects", tuple(self.effects))
        seen = set()
        for effect in self.effects:
            if type(effect) not in SCENE_EFFECTS.values():
                raise ValueError(f"scene {self.name!r}: {type(effect).__name__} is not a scene "
                                 f"effect; expected one of {', '.join(SCENE_EFFECTS)}")
            if effect.effect in seen:
                raise ValueError(f"scene {self.name!r}: effect {effect.effect!r} given twice")
            seen.add(effect.effect)

    # -- effects -------------------------------------------------------------------------------
    def effect(self, name: str):
        """The scene-level effect component called ``name``, or None when the scene lacks it."""
        if name not in SCENE_EFFECTS:
            raise ValueError(f"unknown scene effect {name!r}; known: {', '.join(SCENE_EFFECTS)}")
        for effect in self.effects:
            if effect.effect == name:
                return effect
        return None

    def expanded_objects(self) -> tuple:
        """All objects after the composition effects have added/altered theirs (seeded)."""
        objects = self.objects
        for position, effect in enumerate(self.effects):
            if isinstance(effect, COMPOSITION_EFFECTS):
                rng = np.random.default_rng([self.seed, 0xC0DE, position])
                objects = effect.expand(objects, rng)
        return objects

    @property
    def effect_names(self) -> tuple[str, ...]:
        """Every effect the scene uses (camera, per-object incl. generated objects, scene-level),
        in ``EFFECTS`` order."""
        used = {effect.effect for effect in self.effects}
        if self.camera.effect is not None:
            used.add(self.camera.effect)
        for obj in self.expanded_objects():
            used.update(obj.effects)
        return tuple(name for name in EFFECTS if name in used)

    # -- overrides / serialisation ------------------------------------------------------------
    def with_overrides(self, **overrides: Any) -> "SceneSpec":
        """Copy with ``frames``, ``width``, ``height`` and/or ``seed`` replaced (validated)."""
        allowed = ("frames", "width", "height", "seed")
        for key in overrides:
            if key not in allowed:
                raise ValueError(f"unknown override {key!r} for scene {self.name!r}; "
                                 f"allowed: {', '.join(allowed)}")
        return dataclasses.replace(self, **{k: v for k, v in overrides.items() if v is not None})

    def to_dict(self) -> dict:
        """JSON-ready dict; ``SceneSpec.from_dict(spec.to_dict()) == spec``."""
        path = next(name for name, cls in CAMERA_PATHS.items() if isinstance(self.camera, cls))
        return {
            "name": self.name, "description": self.description, "frames": self.frames,
            "width": self.width, "height": self.height, "fov_deg": self.fov_deg,
            "seed": self.seed, "supersample": self.supersample,
            "camera": {"path": path, **dataclasses.asdict(self.camera)},
            "light": dataclasses.asdict(self.light),
            "objects": [_object_to_dict(obj) for obj in self.objects],
            "effects": {e.effect: dataclasses.asdict(e) for e in self.effects},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "SceneSpec":
        """Build a spec from its JSON form; unknown keys or effects raise ValueError naming them."""
        if not isinstance(data, Mapping):
            raise ValueError(f"scene spec must be a mapping, got {type(data).__name__}")
        _check_keys("scene spec", data, _TOP_LEVEL_KEYS)
        if "name" not in data or "objects" not in data:
            raise ValueError("scene spec needs 'name' and 'objects'")
        kwargs = {k: data[k] for k in ("name", "description", "frames", "width", "height",
                                       "fov_deg", "seed", "supersample") if k in data}
        if "camera" in data:
            kwargs["camera"] = _camera_from_dict(data["camera"])
        if "light" in data:
            kwargs["light"] = _construct(Light, data["light"], "light")
        objects = data["objects"]
        if not isinstance(objects, (list, tuple)):
            raise ValueError("scene spec: 'objects' must be a list")
        kwargs["objects"] = tuple(_object_from_dict(o, f"objects[{i}]")
                                  for i, o in enumerate(objects))
        kwargs["effects"] = _effects_from_dict(data.get("effects", {}))
        return cls(**kwargs)


def _check_keys(where: str, data: Mapping, allowed) -> None:
    for key in data:
        if key not in allowed:
            raise ValueError(f"{where}: unknown key {key!r}; allowed: {', '.join(allowed)}")


def _construct(cls: type, data: Any, where: str):
    """Instantiate dataclass ``cls`` from a dict, naming ``where`` on unknown keys."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ValueError(f"{where} must be a mapping, got {data!r}")
    names = tuple(f.name for f in dataclasses.fields(cls) if f.init)
    _check_keys(where, data, names)
    try:
        return cls(**data)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None


def _camera_from_dict(data: Any) -> CameraPath:
    if not isinstance(data, Mapping):
        raise ValueError(f"camera must be a mapping, got {data!r}")
    path = data.get("path", "static")
    if path not in CAMERA_PATHS:
        raise ValueError(f"camera: unknown path {path!r}; known: {', '.join(CAMERA_PATHS)}")
    return _construct(CAMERA_PATHS[path], {k: v for k, v in data.items() if k != "path"},
                      f"camera ({path})")


def _object_from_dict(data: Any, where: str) -> SceneObject:
    if not isinstance(data, Mapping):
        raise ValueError(f"{where} must be a mapping, got {data!r}")
    allowed = tuple(f.name for f in dataclasses.fields(SceneObject))
    for key in data:
        if key not in allowed:
            hint = ""
            if key in EFFECTS:
                slot = next((s for s, c in OBJECT_EFFECT_SLOTS.items() if c.effect == key), None)
                hint = (f" (effect {key!r} goes in the object's {slot!r} slot)" if slot else
                        f" ({key!r} is not a per-object effect)")
            raise ValueError(f"{where}: unknown key {key!r}{hint}; allowed: {', '.join(allowed)}")
    name = data.get("name", where)
    kwargs = dict(data)
    if "texture" in kwargs:
        kwargs["texture"] = _construct(Texture, kwargs["texture"], f"object {name!r}: texture")
    for slot, slot_cls in OBJECT_EFFECT_SLOTS.items():
        if kwargs.get(slot) is not None:
            kwargs[slot] = _construct(slot_cls, kwargs[slot], f"object {name!r}: {slot}")
    try:
        return SceneObject(**kwargs)
    except TypeError as err:  # missing required name/shape
        raise ValueError(f"{where}: {err}") from None


def _effects_from_dict(data: Any) -> tuple:
    if not isinstance(data, Mapping):
        raise ValueError(f"effects must be a mapping of effect name -> parameters, got {data!r}")
    out = []
    for name, params in data.items():
        if name in SCENE_EFFECTS:
            out.append(_construct(SCENE_EFFECTS[name], params, f"effect {name!r}"))
        elif name in CAMERA_EFFECTS:
            raise ValueError(f"effect {name!r} is a camera path: set camera.path = {name!r}")
        elif name in OBJECT_EFFECTS:
            slot = next(s for s, c in OBJECT_EFFECT_SLOTS.items() if c.effect == name)
            raise ValueError(f"effect {name!r} is per-object: set it in an object's {slot!r} slot")
        else:
            raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    return tuple(out)


def _object_to_dict(obj: SceneObject) -> dict:
    out = {"name": obj.name, "shape": obj.shape, "size": list(obj.size),
           "position": list(obj.position), "rotation_deg": list(obj.rotation_deg),
           "texture": dataclasses.asdict(obj.texture)}
    for slot in OBJECT_EFFECT_SLOTS:
        value = getattr(obj, slot)
        if value is not None:
            out[slot] = dataclasses.asdict(value)
    return out
