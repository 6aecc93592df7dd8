"""Synthetic dynamic-scene simulator with its own analytic renderer and full ground truth.

    from baselines.synthetic import get_scene, list_scenes, simulate
    simulate(get_scene("balloon"), "data/synthetic/balloon")

or ``python -m baselines.synthetic --scene balloon --out data/synthetic/balloon``. A scene
declares its effects (camera path, object motion, lighting change, ...) and only those run.
Output: the NVIDIA/DynamicNeRF layout plus exact depth, flow, occlusion and camera ground truth
(see ``baselines.synthetic.simulate``).
"""
from .camera import Forward, Orbit, Pan, Rig, Shake, StaticCamera, Vrig
from .composition import FastObjects, Occlusion, Textureless, ThinStructures
from .lighting import Light, LightingChange
from .motion import Attachment, NonRigid, RigidMotion, Visibility
from .objects import SceneObject
from .priors import Priors
from .scenes import get_scene, list_scenes
from .simulate import SIMULATOR_VERSION, sample_frame, simulate
from .spec import EFFECTS, SceneSpec
from .textures import Texture

__all__ = [
    "Attachment", "EFFECTS", "FastObjects", "Forward", "Light", "LightingChange", "NonRigid",
    "Occlusion", "Orbit", "Pan", "Priors", "Rig", "RigidMotion", "SIMULATOR_VERSION", "SceneObject",
    "SceneSpec", "Shake", "StaticCamera", "Texture", "Textureless", "ThinStructures",
    "Visibility", "Vrig", "get_scene", "list_scenes", "sample_frame", "simulate",
]
