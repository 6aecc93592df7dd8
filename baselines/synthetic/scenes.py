"""The named scene suite, modelled on the paper's NVIDIA / HyperNeRF cases, plus hard cases.

World frame: y up, floor at y = 0, the action around the origin, cameras near z = 3 looking
towards -z. Every scene sits in a textured room (walls 5 to 9 units from the cameras) with
static props, so camera motion is observable everywhere.
"""
from __future__ import annotations

from typing import Any, Callable

from .camera import Forward, Orbit, Pan, Rig, Shake, StaticCamera, Vrig
from .composition import FastObjects, Occlusion, Textureless, ThinStructures
from .lighting import LightingChange
from .motion import Attachment, NonRigid, RigidMotion, Visibility
from .objects import SceneObject
from .spec import SceneSpec
from .textures import Texture

EYE = (0.0, 1.4, 3.0)
TARGET = (0.0, 1.1, -1.0)


def _set(*objects: SceneObject) -> tuple:
    return tuple(objects)


def _room_and_props() -> tuple:
    """Static background: room, floor, a crate, a pillar and a poster on the back wall."""
    return _set(
        SceneObject("room", "room", size=(3.5, 2.0, 4.5), position=(0.0, 2.0, -0.5),
                    texture=Texture("noise", ((0.82, 0.78, 0.68), (0.35, 0.42, 0.5)),
                                    period=0.45, detail=0.45)),
        SceneObject("floor", "box", size=(3.5, 0.02, 4.5), position=(0.0, 0.0, -0.5),
                    texture=Texture("checker", ((0.78, 0.72, 0.6), (0.32, 0.28, 0.24)),
                                    period=0.4, detail=0.4)),
        SceneObject("crate", "box", size=(0.35, 0.35, 0.35), position=(-1.6, 0.37, -1.8),
                    rotation_deg=(0.0, 25.0, 0.0),
                    texture=Texture("noise", ((0.7, 0.5, 0.25), (0.3, 0.18, 0.08)),
                                    period=0.12, detail=0.3)),
        SceneObject("pillar", "cylinder", size=(0.18, 0.9, 0.18), position=(1.7, 0.92, -2.2),
                    texture=Texture("stripes", ((0.85, 0.85, 0.8), (0.25, 0.35, 0.55)),
                                    period=0.2, detail=0.3, axis=1)),
        SceneObject("poster", "quad", size=(1.2, 0.7, 1.0), position=(0.3, 2.0, -4.98),
                    texture=Texture("checker", ((0.9, 0.3, 0.25), (0.15, 0.2, 0.45)),
                                    period=0.25, detail=0.5)),
    )


def _balloon() -> SceneSpec:
    balloon = SceneObject(
        "balloon", "sphere", size=(0.4, 0.46, 0.4), position=(-0.7, 1.5, 0.2),
        texture=Texture("stripes", ((0.9, 0.15, 0.15), (0.95, 0.85, 0.2)), period=0.16,
                        detail=0.3, axis=1),
        motion=RigidMotion(velocity=(0.9, 0.15, -0.3), oscillation=(0.0, 0.05, 0.0),
                           oscillation_cycles=2.0, spin_deg=60.0, swing_deg=8.0,
                           swing_cycles=1.5))
    string = SceneObject("string", "cylinder", size=(0.012, 0.4, 0.012),
                         position=(0.0, -0.86, 0.0),
                         texture=Texture("flat", ((0.95, 0.95, 0.95), (0.95, 0.95, 0.95))),
                         attach=Attachment("balloon"))
    return SceneSpec(
        name="balloon", frames=32, camera=StaticCamera(EYE, TARGET),
        objects=_room_and_props() + (balloon, string),
        effects=(Shake(rotation_deg=0.6, translation=0.03, cycles=2.0), Vrig((0.3, 0.0, 0.0))),
        description="hand-held camera, a striped balloon on a string drifting slowly (small "
                    "object motion); second vrig camera for HyperNeRF-style testing")


def _playground() -> SceneSpec:
    post = Texture("stripes", ((0.9, 0.9, 0.85), (0.8, 0.2, 0.1)), period=0.15, axis=1)
    objects = _room_and_props() + _set(
        SceneObject("swing_leg_l", "cylinder", size=(0.03, 1.05, 0.03),
                    position=(-0.35, 1.05, -0.6), texture=post),
        SceneObject("swing_leg_r", "cylinder", size=(0.03, 1.05, 0.03),
                    position=(1.15, 1.05, -0.6), texture=post),
        SceneObject("swing_bar", "cylinder", size=(0.03, 0.75, 0.03), position=(0.4, 2.1, -0.6),
                    rotation_deg=(0.0, 0.0, 90.0), texture=post),
        SceneObject("swing", "group", position=(0.4, 2.08, -0.6),
                    motion=RigidMotion(swing_axis=(1.0, 0.0, 0.0), swing_deg=25.0,
                                       swing_cycles=1.5)),
        SceneObject("rope_l", "cylinder", size=(0.012, 0.55, 0.012), position=(-0.25, -0.55, 0.0),
                    texture=Texture("flat", ((0.6, 0.55, 0.45), (0.6, 0.55, 0.45))),
                    attach=Attachment("swing")),
        SceneObject("rope_r", "cylinder", size=(0.012, 0.55, 0.012), position=(0.25, -0.55, 0.0),
                    texture=Texture("flat", ((0.6, 0.55, 0.45), (0.6, 0.55, 0.45))),
                    attach=Attachment("swing")),
        SceneObject("seat", "box", size=(0.3, 0.03, 0.12), position=(0.0, -1.1, 0.0),
                    texture=Texture("checker", ((0.2, 0.6, 0.25), (0.9, 0.85, 0.3)),
                                    period=0.08, detail=0.2),
                    attach=Attachment("swing")),
    )
    return SceneSpec(
        name="playground", frames=36, objects=objects,
        camera=Rig(EYE, TARGET, count=12, baseline=1.6, rows=2, row_spacing=0.3),
        effects=(ThinStructures(anchor=(-1.3, 2.0, -1.2), spread=0.9, ribbons=4, length=0.8,
                                width=0.07, sway=0.35, poles=1),
                 FastObjects(count=3, radius=0.07, center=(0.0, 0.8, 0.3),
                             spread=(1.0, 0.3, 0.5), amplitude=0.7, cycles=4.0)),
        description="12-camera rig with a wide baseline (dominant camera motion), small fast "
                    "balls, thin swaying ribbons, a swinging swing (articulated)")


def _limb(name: str, parent: str, pivot: tuple, size: tuple, phase: float,
          texture: Texture) -> tuple:
    """A swinging limb: a pivot group (hip / shoulder) and the limb hanging from it."""
    joint = SceneObject(f"{name}_joint", "group", position=pivot, attach=Attachment(parent),
                        motion=RigidMotion(swing_axis=(1.0, 0.0, 0.0), swing_deg=25.0,
                                           swing_cycles=3.0, swing_phase_deg=phase))
    limb = SceneObject(name, "box", size=size, position=(0.0, -size[1], 0.0), texture=texture,
                       attach=Attachment(f"{name}_joint"))
    return joint, limb


def _skating() -> SceneSpec:
    jacket = Texture("noise", ((0.15, 0.3, 0.75), (0.9, 0.9, 0.95)), period=0.08, detail=0.3)
    trousers = Texture("stripes", ((0.2, 0.2, 0.25), (0.55, 0.5, 0.45)), period=0.06, axis=1,
                       detail=0.3)
    skater = _set(
        SceneObject("skater", "group", position=(-2.0, 0.0, -0.3),
                    motion=RigidMotion(velocity=(4.0, 0.0, 0.4), oscillation=(0.0, 0.04, 0.0),
                                       oscillation_cycles=3.0, spin_deg=-20.0)),
        SceneObject("torso", "box", size=(0.17, 0.3, 0.1), position=(0.0, 1.05, 0.0),
                    texture=jacket, attach=Attachment("skater")),
        SceneObject("head", "sphere", size=(0.12, 0.14, 0.12), position=(0.0, 1.5, 0.0),
                    texture=Texture("noise", ((0.95, 0.8, 0.65), (0.5, 0.3, 0.2)), period=0.05,
                                    detail=0.2),
                    attach=Attachment("skater")),
        *_limb("leg_l", "skater", (-0.08, 0.75, 0.0), (0.06, 0.36, 0.06), 0.0, trousers),
        *_limb("leg_r", "skater", (0.08, 0.75, 0.0), (0.06, 0.36, 0.06), 180.0, trousers),
        *_limb("arm_l", "skater", (-0.22, 1.32, 0.0), (0.04, 0.27, 0.04), 180.0, jacket),
        *_limb("arm_r", "skater", (0.22, 1.32, 0.0), (0.04, 0.27, 0.04), 0.0, jacket),
    )
    return SceneSpec(
        name="skating", frames=36, objects=_room_and_props() + skater,
        camera=Rig(EYE, TARGET, count=12, baseline=1.0, rows=2, row_spacing=0.25),
        effects=(Occlusion(position=(0.5, 0.9, 0.9), size=(0.1, 0.9, 0.1)),),
        description="12-camera rig; an articulated skater crossing the whole view, passing "
                    "behind a pillar (occlusion)")


def _truck() -> SceneSpec:
    wheel_texture = Texture("checker", ((0.1, 0.1, 0.1), (0.7, 0.7, 0.7)), period=0.09)
    travel = 3.0
    roll_deg = -travel / 0.2 * 180.0 / 3.141592653589793  # rolling without slipping, radius 0.2
    wheels = tuple(
        SceneObject(f"wheel{k}", "cylinder", size=(0.2, 0.05, 0.2),
                    position=(x, 0.2, z), rotation_deg=(90.0, 0.0, 0.0), texture=wheel_texture,
                    attach=Attachment("truck"), motion=RigidMotion(spin_deg=roll_deg))
        for k, (x, z) in enumerate([(-0.6, 0.43), (0.55, 0.43), (-0.6, -0.43), (0.55, -0.43)]))
    truck = _set(
        SceneObject("truck", "group", position=(-1.6, 0.0, -0.8),
                    motion=RigidMotion(velocity=(travel, 0.0, 0.0))),
        SceneObject("cargo", "box", size=(0.75, 0.38, 0.42), position=(-0.2, 0.64, 0.0),
                    texture=Texture("stripes", ((0.9, 0.55, 0.1), (0.95, 0.9, 0.8)), period=0.2,
                                    detail=0.4),
                    attach=Attachment("truck")),
        SceneObject("cabin", "box", size=(0.28, 0.3, 0.4), position=(0.85, 0.56, 0.0),
                    texture=Texture("noise", ((0.7, 0.1, 0.1), (0.95, 0.6, 0.5)), period=0.1,
                                    detail=0.3),
                    attach=Attachment("truck")),
    ) + wheels
    return SceneSpec(
        name="truck", frames=36, objects=_room_and_props() + truck,
        camera=Rig(EYE, TARGET, count=12, baseline=1.2, rows=2, row_spacing=0.25),
        description="12-camera rig; a large rigid truck translating across the view with "
                    "rolling wheels")


def _umbrella() -> SceneSpec:
    umbrella = _set(
        SceneObject("umbrella", "group", position=(0.2, 1.45, -0.2),
                    motion=RigidMotion(spin_deg=45.0, swing_axis=(0.0, 0.0, 1.0), swing_deg=6.0)),
        SceneObject("canopy", "sphere", size=(0.7, 0.22, 0.7), position=(0.0, 0.15, 0.0),
                    texture=Texture("stripes", ((0.15, 0.2, 0.6), (0.95, 0.95, 0.9)),
                                    period=0.25, detail=0.3),
                    deform=NonRigid(scale_start=(0.25, 2.0, 0.25), scale_end=(1.0, 1.0, 1.0)),
                    attach=Attachment("umbrella")),
        SceneObject("shaft", "cylinder", size=(0.015, 0.55, 0.015), position=(0.0, -0.35, 0.0),
                    texture=Texture("flat", ((0.3, 0.3, 0.3), (0.3, 0.3, 0.3))),
                    attach=Attachment("umbrella")),
        SceneObject("handle", "cylinder", size=(0.03, 0.08, 0.03), position=(0.0, -0.95, 0.0),
                    texture=Texture("noise", ((0.4, 0.25, 0.1), (0.2, 0.1, 0.05)), period=0.03),
                    attach=Attachment("umbrella")),
    )
    return SceneSpec(
        name="umbrella", frames=36, objects=_room_and_props() + umbrella,
        camera=Rig(EYE, TARGET, count=12, baseline=0.8, rows=2, row_spacing=0.25),
        description="12-camera rig; an umbrella opening (non-rigid scaling of the canopy) while "
                    "turning")


def _static() -> SceneSpec:
    return SceneSpec(
        name="static", frames=24, objects=_room_and_props(),
        camera=Orbit(target=(0.0, 1.0, -1.0), radius=4.0, height=0.4, start_deg=-15.0,
                     sweep_deg=30.0),
        description="no dynamic content; the camera orbits a static room (control scene)")


def _hard_appear() -> SceneSpec:
    objects = _room_and_props() + _set(
        SceneObject("newcomer", "sphere", size=(0.3, 0.3, 0.3), position=(-0.6, 1.2, 0.0),
                    texture=Texture("checker", ((0.95, 0.75, 0.2), (0.3, 0.1, 0.5)), period=0.12,
                                    detail=0.3),
                    motion=RigidMotion(velocity=(0.6, 0.0, 0.0), spin_deg=90.0),
                    visibility=Visibility(appear=0.3)),
        SceneObject("leaver", "box", size=(0.25, 0.25, 0.25), position=(0.8, 0.6, -0.4),
                    texture=Texture("noise", ((0.2, 0.7, 0.3), (0.9, 0.95, 0.6)), period=0.1,
                                    detail=0.3),
                    motion=RigidMotion(spin_deg=120.0), visibility=Visibility(disappear=0.65)),
        SceneObject("runner", "sphere", size=(0.2, 0.2, 0.2), position=(-1.2, 0.5, -0.6),
                    texture=Texture("stripes", ((0.9, 0.2, 0.6), (0.2, 0.2, 0.2)), period=0.08),
                    motion=RigidMotion(velocity=(2.4, 0.0, 0.0))),
    )
    return SceneSpec(
        name="hard_appear", frames=24, objects=objects,
        camera=Pan(EYE, TARGET, sweep_deg=12.0),
        effects=(Occlusion(position=(0.1, 0.9, 1.0), size=(0.12, 0.9, 0.12)),),
        description="objects appearing and disappearing mid-sequence, a ball running behind an "
                    "occluder, panning camera")


def _hard_textureless() -> SceneSpec:
    objects = _room_and_props() + _set(
        SceneObject("blob", "box", size=(0.35, 0.3, 0.3), position=(-0.5, 1.0, -0.5),
                    texture=Texture("noise", ((0.2, 0.55, 0.8), (0.2, 0.55, 0.8))),
                    motion=RigidMotion(velocity=(1.0, 0.2, 0.0), spin_deg=70.0)),
    )
    return SceneSpec(
        name="hard_textureless", frames=24, objects=objects,
        camera=Forward(EYE, TARGET, distance=0.8),
        effects=(Textureless(objects=("blob",), panel=(-0.4, 1.7, -3.5),
                             panel_size=(1.6, 1.0, 1.0)),),
        description="a flat-coloured moving box in front of a large flat panel (no photometric "
                    "signal), camera moving forward")


def _hard_fast() -> SceneSpec:
    objects = _room_and_props() + _set(
        SceneObject("projectile", "box", size=(0.15, 0.15, 0.15), position=(-2.2, 1.3, -0.5),
                    texture=Texture("checker", ((0.95, 0.95, 0.9), (0.8, 0.1, 0.1)), period=0.07),
                    motion=RigidMotion(velocity=(4.8, -0.4, 0.0), spin_deg=540.0)),
    )
    return SceneSpec(
        name="hard_fast", frames=24, objects=objects, camera=StaticCamera(EYE, TARGET),
        effects=(Shake(rotation_deg=0.8, translation=0.04, cycles=3.0),
                 FastObjects(count=2, radius=0.1, center=(0.0, 1.0, 0.0), spread=(0.6, 0.3, 0.3),
                             amplitude=0.9, cycles=6.0)),
        description="very fast motion: a projectile crossing the view and balls moving tens of "
                    "pixels per frame, hand-held camera")


def _hard_baseline() -> SceneSpec:
    objects = _room_and_props() + _set(
        SceneObject("drifter", "sphere", size=(0.3, 0.3, 0.3), position=(0.0, 1.1, -0.3),
                    texture=Texture("noise", ((0.9, 0.4, 0.1), (0.2, 0.1, 0.4)), period=0.1,
                                    detail=0.3),
                    motion=RigidMotion(velocity=(0.5, 0.0, 0.0), spin_deg=45.0)),
    )
    return SceneSpec(
        name="hard_baseline", frames=24, objects=objects,
        camera=Rig(EYE, TARGET, count=4, baseline=3.0, rows=1),
        description="4-camera rig with a 3-unit baseline: huge viewpoint jumps between "
                    "consecutive frames")


def _hard_lighting() -> SceneSpec:
    objects = _room_and_props() + _set(
        SceneObject("ball", "sphere", size=(0.3, 0.3, 0.3), position=(-0.4, 1.1, -0.2),
                    texture=Texture("checker", ((0.9, 0.9, 0.9), (0.2, 0.3, 0.7)), period=0.12,
                                    detail=0.3),
                    motion=RigidMotion(velocity=(0.8, 0.0, 0.0), spin_deg=90.0)),
    )
    return SceneSpec(
        name="hard_lighting", frames=24, objects=objects, camera=StaticCamera(EYE, TARGET),
        effects=(LightingChange(gain_start=1.0, gain_end=0.55, flicker=0.15, flicker_cycles=3.0,
                                sweep_deg=60.0),),
        description="global lighting change (dimming, flicker, moving light) breaks brightness "
                    "constancy")


_BUILDERS: dict[str, Callable[[], SceneSpec]] = {
    "balloon": _balloon, "playground": _playground, "skating": _skating, "truck": _truck,
    "umbrella": _umbrella, "static": _static, "hard_appear": _hard_appear,
    "hard_textureless": _hard_textureless, "hard_fast": _hard_fast,
    "hard_baseline": _hard_baseline, "hard_lighting": _hard_lighting,
}


def list_scenes() -> dict[str, str]:
    """Scene name -> one-line description, in suite order."""
    return {name: build().description for name, build in _BUILDERS.items()}


def get_scene(name: str, **overrides: Any) -> SceneSpec:
    """The named scene, with optional ``frames``, ``width``, ``height``, ``seed`` overrides."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(_BUILDERS)}")
    return _BUILDERS[name]().with_overrides(**overrides)
