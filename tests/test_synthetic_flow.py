"""Ground-truth flow and occlusion of the synthetic simulator are exact."""
from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from baselines.synthetic import (Attachment, NonRigid, Pan, RigidMotion, SceneObject, SceneSpec,
                                 Shake, StaticCamera, Texture, Visibility, get_scene, simulate)
from baselines.synthetic.simulate import sample_frame

EYE, TARGET = (0.0, 1.4, 3.0), (0.0, 1.1, -1.0)


def _room() -> SceneObject:
    return SceneObject("room", "room", size=(3.5, 2.0, 4.5), position=(0.0, 2.0, -0.5),
                       texture=Texture("noise", ((0.9, 0.8, 0.6), (0.2, 0.3, 0.5)), period=0.8))


def _motion_spec() -> SceneSpec:
    """Hand-held camera; a spinning ball (rigid), a swaying, growing ribbon (non-rigid) carried by
    a moving group (articulated). Smooth textures keep bilinear resampling error small."""
    objects = (
        _room(),
        SceneObject("crate", "box", size=(0.4, 0.4, 0.4), position=(-1.2, 0.4, -1.5),
                    rotation_deg=(0.0, 30.0, 0.0),
                    texture=Texture("noise", ((0.9, 0.5, 0.2), (0.2, 0.1, 0.05)), period=0.3)),
        SceneObject("ball", "sphere", size=(0.45, 0.45, 0.45), position=(-0.3, 1.2, 0.0),
                    texture=Texture("noise", ((0.95, 0.9, 0.2), (0.6, 0.1, 0.3)), period=0.25),
                    motion=RigidMotion(velocity=(0.8, 0.1, 0.0), spin_deg=40.0)),
        SceneObject("carrier", "group", position=(0.9, 1.6, -0.5),
                    motion=RigidMotion(velocity=(-0.3, -0.2, 0.0))),
        SceneObject("flag", "quad", size=(0.35, 0.5, 1.0), position=(0.0, -0.5, 0.0),
                    rotation_deg=(0.0, 20.0, 0.0),
                    texture=Texture("noise", ((0.2, 0.8, 0.4), (0.9, 0.9, 0.9)), period=0.2),
                    attach=Attachment("carrier"),
                    deform=NonRigid(scale_start=(0.8, 1.0, 1.0), scale_end=(1.2, 0.9, 1.0),
                                    shear=0.4, shear_anchor=0.5, shear_cycles=1.0)),
    )
    return SceneSpec(name="flowtest", objects=objects, camera=StaticCamera(EYE, TARGET),
                     effects=(Shake(rotation_deg=2.5, translation=0.1),), frames=6, width=48,
                     height=48, supersample=3)


@pytest.fixture(scope="module")
def motion_scene(tmp_path_factory):
    spec = _motion_spec()
    return spec, simulate(spec, tmp_path_factory.mktemp("flow") / "scene", progress=False)


def _image(root, i):
    return cv2.imread(str(root / "images" / f"{i:03d}.png"))[:, :, ::-1].astype(np.float32) / 255


def _flow(root, kind, i):
    flow = np.load(root / "gt" / f"flow_{kind}" / f"{i:03d}.npy")
    occluded = cv2.imread(str(root / "gt" / f"occ_{kind}" / f"{i:03d}.png"), cv2.IMREAD_GRAYSCALE)
    return flow, occluded > 0


def _centres(w, h):
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.stack([jj, ii], axis=-1)


@pytest.mark.parametrize("kind,step", [("fwd", 1), ("bwd", -1)])
def test_flow_warps_exact_renders_onto_each_other(motion_scene, kind, step):
    """Point-sampling frame t+-1 at q + F(q) reproduces frame t at q (up to the shading change of
    rotating normals), far better than assuming no motion."""
    spec, _ = motion_scene
    root = motion_scene[1]
    centres = _centres(spec.width, spec.height).reshape(-1, 2)
    errors, zero_errors = [], []
    frames = range(spec.frames - 1) if step == 1 else range(1, spec.frames)
    for t in frames:
        flow, occluded = _flow(root, kind, t)
        visible = ~occluded.reshape(-1)
        assert visible.mean() > 0.8
        here, _ = sample_frame(spec, t, centres)
        there, _ = sample_frame(spec, t + step, centres + flow.reshape(-1, 2))
        still, _ = sample_frame(spec, t + step, centres)
        errors.append(np.abs(there - here)[visible].mean())
        zero_errors.append(np.abs(still - here)[visible].mean())
    assert max(errors) < 2e-3
    assert max(errors) < 0.05 * min(zero_errors)


@pytest.mark.parametrize("kind,step", [("fwd", 1), ("bwd", -1)])
def test_flow_bilinear_warp_of_stored_images(motion_scene, kind, step):
    """I_{t+-1}(q + F(q)) sampled bilinearly from the PNGs matches I_t(q) on non-occluded pixels;
    zero flow gives a much larger error."""
    spec, root = motion_scene
    jj, ii = np.meshgrid(np.arange(spec.width, dtype=np.float32),
                         np.arange(spec.height, dtype=np.float32))
    frames = range(spec.frames - 1) if step == 1 else range(1, spec.frames)
    for t in frames:
        flow, occluded = _flow(root, kind, t)
        current, other = _image(root, t), _image(root, t + step)
        warped = cv2.remap(other, jj + flow[..., 0], ii + flow[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
        visible = ~occluded
        error = np.abs(warped - current)[visible].mean()
        zero_error = np.abs(other - current)[visible].mean()
        assert error < 0.015, (t, error)
        assert error < 0.25 * zero_error, (t, error, zero_error)


def test_pure_pan_gives_rotation_homography(tmp_path):
    """A camera turning about its centre over a static scene: flow = K R_b R_a^T K^-1 q - q."""
    spec = dataclasses.replace(get_scene("static", frames=4, width=40, height=32),
                               camera=Pan(EYE, TARGET, sweep_deg=15.0))
    root = simulate(spec, tmp_path / "pan", progress=False)
    cams = json.loads((root / "gt" / "cameras.json").read_text())["frames"]
    q = np.concatenate([_centres(40, 32), np.ones((32, 40, 1))], axis=-1).reshape(-1, 3)
    for kind, step in (("fwd", 1), ("bwd", -1)):
        for a in range(spec.frames):
            b = a + step
            if not 0 <= b < spec.frames:
                continue
            K = np.array(cams[a]["K"])
            Ra = np.array(cams[a]["viewmat"])[:3, :3]
            Rb = np.array(cams[b]["viewmat"])[:3, :3]
            centre_a = -Ra.T @ np.array(cams[a]["viewmat"])[:3, 3]
            centre_b = -Rb.T @ np.array(cams[b]["viewmat"])[:3, 3]
            np.testing.assert_allclose(centre_a, centre_b, atol=1e-12)  # a pure rotation
            mapped = q @ (K @ Rb @ Ra.T @ np.linalg.inv(K)).T
            expected = (mapped[:, :2] / mapped[:, 2:] - q[:, :2]).reshape(32, 40, 2)
            flow, occluded = _flow(root, kind, a)
            assert np.abs(flow).max() > 1.0  # the camera did turn
            np.testing.assert_allclose(flow, expected, atol=2e-4)
            target = expected + _centres(40, 32)
            outside = ((target[..., 0] < 0) | (target[..., 0] >= 40) | (target[..., 1] < 0)
                       | (target[..., 1] >= 32))
            # Pure rotation occludes nothing: exactly the pixels leaving the image are flagged.
            np.testing.assert_array_equal(occluded, outside)


def test_disappearing_object_is_occluded(tmp_path):
    """Points of an object absent at t+1 are occluded; before that, the static object is not."""
    ghost = SceneObject("ghost", "box", size=(0.3, 0.3, 0.3), position=(0.4, 1.2, 0.0),
                        texture=Texture("checker", period=0.2),
                        visibility=Visibility(disappear=0.5))
    spec = SceneSpec(name="ghost", objects=(_room(), ghost), camera=StaticCamera(EYE, TARGET),
                     frames=5, width=32, height=32, supersample=1)
    root = simulate(spec, tmp_path / "ghost", progress=False)
    masks = [cv2.imread(str(root / "motion_masks" / f"{t:03d}.png"), cv2.IMREAD_GRAYSCALE) > 0
             for t in range(spec.frames)]
    assert masks[0].any() and masks[1].any() and not masks[2].any()
    flow, occluded = _flow(root, "fwd", 0)  # t = 0 -> 0.25: still there, nothing moves
    assert not occluded[masks[0]].any()
    np.testing.assert_allclose(flow[masks[0]], 0.0, atol=1e-4)
    _, occluded = _flow(root, "fwd", 1)  # t = 0.25 -> 0.5: gone
    assert occluded[masks[1]].all()
    _, occluded = _flow(root, "bwd", 2)  # the background revealed at t = 0.5 was hidden at 0.25
    assert occluded[masks[1]].all() and not occluded[~masks[1]].any()


def test_occlusion_matches_depth_at_the_landing_point(tmp_path):
    """A ball sliding behind a panel (static camera, translation across the view, so each ball
    point keeps its z-depth): a pixel is occluded at t+1 exactly when t+1 shows something nearer
    where the point lands, or the point leaves the image."""
    ball = SceneObject("ball", "sphere", size=(0.4, 0.4, 0.4), position=(-1.0, 1.1, -1.0),
                       texture=Texture("noise", period=0.2),
                       motion=RigidMotion(velocity=(2.0, 0.0, 0.0)))
    panel = SceneObject("panel", "box", size=(0.25, 0.8, 0.05), position=(0.0, 1.1, 0.5),
                        texture=Texture("stripes", period=0.1))
    spec = SceneSpec(name="occ", objects=(_room(), ball, panel), camera=StaticCamera(EYE, TARGET),
                     frames=5, width=48, height=40, supersample=1)
    root = simulate(spec, tmp_path / "occ", progress=False)
    centres = _centres(48, 40).reshape(-1, 2)
    seen_both = False
    for t in range(spec.frames - 1):
        flow, occluded = _flow(root, "fwd", t)
        mask = (cv2.imread(str(root / "motion_masks" / f"{t:03d}.png"),
                           cv2.IMREAD_GRAYSCALE) > 0).reshape(-1)
        depth = np.load(root / "gt" / "depth" / f"{t:03d}.npy").reshape(-1)
        landing = centres + flow.reshape(-1, 2)
        _, seen = sample_frame(spec, t + 1, landing)
        leaves = ((landing[:, 0] < 0) | (landing[:, 0] >= 48) | (landing[:, 1] < 0)
                  | (landing[:, 1] >= 40))
        expected = leaves | (seen < depth * (1.0 - 1e-4))
        np.testing.assert_array_equal(occluded.reshape(-1)[mask], expected[mask])
        seen_both |= bool(expected[mask].any() and (~expected[mask]).any())
    assert seen_both  # the scene really has the ball both visible and hidden
