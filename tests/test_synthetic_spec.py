"""Scene specs, the named suite, the CLI and "an absent effect never runs"."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from baselines.synthetic import (EFFECTS, Attachment, FastObjects, Forward, LightingChange,
                                 NonRigid, Occlusion, Orbit, Pan, Rig, RigidMotion, SceneObject,
                                 SceneSpec, Shake, StaticCamera, Texture, Textureless,
                                 ThinStructures, Visibility, Vrig, get_scene, list_scenes, simulate)
from baselines.synthetic.__main__ import main

REQUIRED_SCENES = {"balloon", "playground", "skating", "truck", "umbrella", "static",
                   "hard_appear", "hard_textureless", "hard_fast", "hard_baseline"}


def test_suite_names_and_effects():
    scenes = list_scenes()
    assert REQUIRED_SCENES <= set(scenes)
    assert all(isinstance(d, str) and d for d in scenes.values())
    effects = {name: set(get_scene(name).effect_names) for name in scenes}
    assert effects["static"] == {"orbit"}
    assert {"shake", "vrig"} <= effects["balloon"]
    assert {"rig", "fast_objects", "thin_structures"} <= effects["playground"]
    assert "nonrigid" in effects["umbrella"] and "appearance" in effects["hard_appear"]
    assert "textureless" in effects["hard_textureless"]
    assert "rig" in effects["skating"] and "rig" in effects["truck"]
    assert set().union(*effects.values()) == set(EFFECTS)  # every effect appears in the suite


def test_get_scene_overrides_and_dict_round_trip():
    spec = get_scene("playground", frames=5, width=20, height=10, seed=3)
    assert (spec.frames, spec.width, spec.height, spec.seed) == (5, 20, 10, 3)
    data = json.loads(json.dumps(spec.to_dict()))
    assert SceneSpec.from_dict(data) == spec


@pytest.mark.parametrize("call,culprit", [
    (lambda: get_scene("ballon"), "ballon"),
    (lambda: get_scene("balloon", frames=0), "frames"),
    (lambda: get_scene("balloon", frames=1), "frames"),
    (lambda: get_scene("balloon", width=-4), "width"),
    (lambda: get_scene("balloon", height=0), "height"),
    (lambda: get_scene("balloon", seed=-1), "seed"),
    (lambda: get_scene("balloon", fps=3), "fps"),
    (lambda: SceneSpec.from_dict({**get_scene("static").to_dict(), "effects": {"wobble": {}}}),
     "wobble"),
    (lambda: SceneSpec.from_dict({**get_scene("static").to_dict(), "effects": {"pan": {}}}),
     "camera path"),
    (lambda: SceneSpec.from_dict({**get_scene("static").to_dict(),
                                  "camera": {"path": "dolly"}}), "dolly"),
    (lambda: SceneSpec.from_dict({**get_scene("static").to_dict(), "colour": 1}), "colour"),
    (lambda: SceneSpec.from_dict({**get_scene("static").to_dict(), "objects": [
        {"name": "ball", "shape": "sphere", "motion": {"velocty": [1, 0, 0]}}]}), "velocty"),
    (lambda: SceneSpec.from_dict({**get_scene("static").to_dict(), "objects": [
        {"name": "ball", "shape": "torus"}]}), "shape"),
    (lambda: SceneObject("ball", "sphere", size=(1.0, 0.0, 1.0)), "size"),
    (lambda: Shake(rotation_deg=-1.0), "rotation_deg"),
    (lambda: NonRigid(scale_end=(1.0, 0.0, 1.0)), "scale_end"),
    (lambda: Visibility(appear=0.7, disappear=0.2), "appear"),
    (lambda: Texture("marble"), "kind"),
])
def test_bad_specs_raise_value_error_naming_the_culprit(call, culprit):
    with pytest.raises(ValueError, match=culprit):
        call()


def test_bad_object_graph_is_rejected_before_rendering(tmp_path):
    base = get_scene("static", frames=2, width=8, height=8)
    orphan = SceneObject("orphan", "sphere", attach=Attachment("nobody"))
    with pytest.raises(ValueError, match="nobody"):
        simulate(dataclasses.replace(base, objects=base.objects + (orphan,)), tmp_path / "x")
    twin = dataclasses.replace(base, objects=base.objects + (base.objects[-1],))
    with pytest.raises(ValueError, match="duplicate"):
        simulate(twin, tmp_path / "y")
    unknown = dataclasses.replace(base, effects=(Textureless(objects=("ghost",)),))
    with pytest.raises(ValueError, match="ghost"):
        simulate(unknown, tmp_path / "z")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv,culprit", [
    (["--scene", "balloon", "--out", "{out}", "--size", "64x"], "--size"),
    (["--scene", "balloon", "--out", "{out}", "--size", "0x32"], "--size"),
    (["--scene", "balloon", "--out", "{out}", "--size", "-8x32"], "--size"),
    (["--scene", "nope", "--out", "{out}"], "nope"),
    (["--scene", "balloon", "--out", "{out}", "--frames", "0"], "frames"),
    (["--scene", "balloon"], "--out"),
    (["--scene", "balloon", "--out", "{out}", "--frames", "many"], "--frames"),
    (["--out", "{out}"], "--scene"),
])
def test_cli_errors_are_one_line_and_nonzero(tmp_path, capsys, argv, culprit):
    code = main([a.replace("{out}", str(tmp_path / "out")) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert len(err.splitlines()) == 1 and err.startswith("error:") and culprit in err
    assert not (tmp_path / "out").exists()


def test_cli_list_prints_one_line_per_scene(capsys):
    assert main(["--list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == len(list_scenes())
    for line, (name, description) in zip(lines, list_scenes().items()):
        assert line.split()[0] == name and line.endswith(description)
        assert ",".join(get_scene(name).effect_names) in line


def test_cli_module_entry_point_fails_with_one_line(tmp_path):
    bad = subprocess.run([sys.executable, "-m", "baselines.synthetic", "--scene", "balloon",
                          "--out", str(tmp_path / "o"), "--size", "12by12"],
                         capture_output=True, text=True)
    assert bad.returncode != 0
    assert bad.stderr.strip().splitlines() == [bad.stderr.strip()] and "--size" in bad.stderr
    assert not (tmp_path / "o").exists()


def test_cli_generates_from_name_and_from_spec_file(tmp_path, capsys):
    assert main(["--scene", "static", "--out", str(tmp_path / "a"), "--frames", "3",
                 "--size", "16x12", "--seed", "2", "--quiet"]) == 0
    written = json.loads((tmp_path / "a" / "scene.json").read_text())
    assert (written["frames"], written["width"], written["height"], written["seed"]) == (3, 16, 12, 2)
    # A scene.json is itself a valid --spec input and reproduces the same scene.
    assert main(["--spec", str(tmp_path / "a" / "scene.json"), "--out", str(tmp_path / "b"),
                 "--quiet"]) == 0
    assert ((tmp_path / "a" / "images" / "002.png").read_bytes()
            == (tmp_path / "b" / "images" / "002.png").read_bytes())


# -- an absent effect never runs -------------------------------------------------------------

class EffectCalled(Exception):
    pass


def _base() -> SceneSpec:
    room = SceneObject("room", "room", size=(3.5, 2.0, 4.5), position=(0.0, 2.0, -0.5),
                       texture=Texture("checker", period=0.5))
    ball = SceneObject("ball", "sphere", size=(0.3, 0.3, 0.3), position=(0.0, 1.1, 0.0))
    return SceneSpec(name="bare", objects=(room, ball), camera=StaticCamera(), frames=3,
                     width=12, height=10, supersample=1)


def _with_object_effect(**slots) -> SceneSpec:
    base = _base()
    ball = dataclasses.replace(base.objects[1], **slots)
    return dataclasses.replace(base, objects=(base.objects[0], ball))


def _one_effect_scenes() -> dict[str, SceneSpec]:
    base = _base()
    child = SceneObject("hat", "box", size=(0.1, 0.1, 0.1), position=(0.0, 0.4, 0.0),
                        attach=Attachment("ball"))
    return {
        "pan": dataclasses.replace(base, camera=Pan()),
        "orbit": dataclasses.replace(base, camera=Orbit()),
        "forward": dataclasses.replace(base, camera=Forward()),
        "rig": dataclasses.replace(base, camera=Rig(count=2, rows=1)),
        "rigid": _with_object_effect(motion=RigidMotion(velocity=(0.5, 0.0, 0.0))),
        "nonrigid": _with_object_effect(deform=NonRigid(scale_end=(1.5, 1.0, 1.0))),
        "articulated": dataclasses.replace(base, objects=base.objects + (child,)),
        "appearance": _with_object_effect(visibility=Visibility(appear=0.4)),
        "shake": dataclasses.replace(base, effects=(Shake(),)),
        "vrig": dataclasses.replace(base, effects=(Vrig(),)),
        "lighting": dataclasses.replace(base, effects=(LightingChange(),)),
        "thin_structures": dataclasses.replace(base, effects=(ThinStructures(sway=0.0),)),
        "fast_objects": dataclasses.replace(base, effects=(FastObjects(),)),
        "occlusion": dataclasses.replace(base, effects=(Occlusion(),)),
        "textureless": dataclasses.replace(base, effects=(Textureless(objects=("ball",)),)),
    }


def _spy_on_every_effect(monkeypatch) -> None:
    """Replace every method and property of every effect class with one that raises."""
    for name, cls in EFFECTS.items():
        for attr, value in list(vars(cls).items()):
            if attr.startswith("__") or not (callable(value) or isinstance(value, property)):
                continue

            def boom(*args, _name=name, _attr=attr, **kwargs):
                raise EffectCalled(f"{_name}: {_attr}")

            monkeypatch.setattr(cls, attr, property(boom) if isinstance(value, property) else boom)


def test_absent_effects_never_run(tmp_path, monkeypatch):
    """With every effect's code booby-trapped, a scene without effects still renders; and each
    one-effect scene trips exactly its own effect, so the traps are live."""
    bare = _base()
    scenes = _one_effect_scenes()
    assert set(scenes) == set(EFFECTS)
    for name, spec in scenes.items():
        assert name in spec.effect_names
    assert bare.effect_names == ()
    _spy_on_every_effect(monkeypatch)
    root = simulate(bare, tmp_path / "bare", progress=False)
    assert json.loads((root / "scene.json").read_text())["effects"] == []
    for name, spec in scenes.items():
        with pytest.raises(EffectCalled, match=f"^{name}:"):
            simulate(spec, tmp_path / name, progress=False)
