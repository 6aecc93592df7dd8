"""Render a scene spec into the NVIDIA/DynamicNeRF layout plus ground truth.

Layout (N frames, stems 000, 001, ...):

    poses_bounds.npy          [N,17] LLFF: c2w 3x4 with columns [down, right, back, t], then
                              [H, W, focal]; then near, far (bounds of that frame's depth)
    images/000.png            RGB uint8
    disp/000.npy              float32 [H,W] disparity 1 / depth (priors="real": a monocular
                              network's, see priors.py)
    motion_masks/000.png      uint8, 255 = dynamic object (left out with priors="real")
    gt/motion_masks/000.png   the same exact masks, for evaluation (always written)
    gt/depth/000.npy          float32 [H,W] camera z-depth
    gt/flow_fwd/000.npy       float32 [H,W,2] (dx, dy) frame t -> t+1 (t < N-1)
    gt/occ_fwd/000.png        uint8, 255 = occluded at t+1 / leaves the image
    gt/flow_bwd/001.npy       float32 [H,W,2] frame t -> t-1 (t >= 1); gt/occ_bwd/001.png
    gt/cameras.json           per frame: K, viewmat (world -> camera, OpenCV), time, camera_id, ...
    gt/split.json             test = frames with i % 8 == 0 (llffhold), train = the rest
    gt/vrig/                  second camera (vrig effect): images/, depth/, cameras.json
    scene.json                the spec, seed, effects, simulator version, priors, scene scale

`scene_scale` S multiplies every world length written (camera positions, bounds, depths): the
images and flows stay the same, as in a capture whose reconstruction has other units.
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Optional, Union

import numpy as np
from tqdm import tqdm

from .flow import scene_flow
from .lighting import light_at
from .priors import Priors
from .raycast import FrameCamera, Hits, cast, shade
from .scene import BuiltScene
from .spec import SceneSpec
from .transforms import c2w_to_llff, intrinsics
from .writer import (check_destination, frame_name, mask_png, publish, staging_dir, to_uint8,
                     write_json, write_npy, write_png)

SIMULATOR_VERSION = "1.0"
LLFF_HOLD = 8
# Per-frame bounds in poses_bounds.npy: the frame's depth range widened by these factors.
_NEAR_FACTOR, _FAR_FACTOR = 0.9, 1.1


def frame_cameras(spec: SceneSpec) -> list[FrameCamera]:
    """The main camera of every frame (path, then hand-held shake when the scene has it)."""
    K = intrinsics(spec.width, spec.height, spec.fov_deg)
    shake = spec.effect("shake")
    cameras = []
    for i in range(spec.frames):
        t = i / (spec.frames - 1)
        c2w, camera_id = spec.camera.pose(i, t)
        if shake is not None:
            c2w = shake.perturb(c2w, t, spec.seed)
        cameras.append(FrameCamera(K=K, c2w=c2w, width=spec.width, height=spec.height, time=t,
                                   camera_id=camera_id))
    return cameras


def vrig_cameras(spec: SceneSpec, main: list[FrameCamera]) -> Optional[list[FrameCamera]]:
    """The second (validation-rig) camera of every frame, or None without the vrig effect."""
    vrig = spec.effect("vrig")
    if vrig is None:
        return None
    camera_id = spec.camera.camera_count  # ids after the main camera(s)
    return [FrameCamera(K=cam.K, c2w=vrig.second_camera(cam.c2w), width=cam.width,
                        height=cam.height, time=cam.time, camera_id=camera_id) for cam in main]


def _subpixel_offsets(s: int) -> list[tuple[float, float]]:
    """s x s stratified sample positions inside a pixel (regular grid)."""
    ticks = [(k + 0.5) / s for k in range(s)]
    return [(x, y) for y in ticks for x in ticks]


class _Renderer:
    """Renders colour and centre-ray geometry of one scene (shared state across frames)."""

    def __init__(self, spec: SceneSpec, scene: BuiltScene):
        self.spec, self.scene = spec, scene
        self.offsets = _subpixel_offsets(spec.supersample)
        # With odd s the centre ray is one of the samples: reuse it instead of casting twice.
        self.centre_sample = (len(self.offsets) // 2) if spec.supersample % 2 == 1 else None
        self.lighting = spec.effect("lighting")

    def render(self, cam: FrameCamera, placements, frame_label: str):
        """-> (rgb [H,W,3] float in [0,1], centre Hits [H*W])."""
        h, w, n_sub = cam.height, cam.width, len(self.offsets)
        light = light_at(self.spec.light, self.lighting, cam.time)
        dirs = cam.directions(cam.pixel_grid(self.offsets))
        hits = cast(placements, cam.center, dirs)
        color = shade(hits, dirs, placements, self.scene.objects, self.scene.texture_seeds, light)
        rgb = color.reshape(h, w, n_sub, 3).mean(axis=2)
        if self.centre_sample is not None:
            pick = np.arange(h * w) * n_sub + self.centre_sample
            centre = Hits(depth=hits.depth[pick], index=hits.index[pick], local=hits.local[pick])
        else:
            centre = cast(placements, cam.center, cam.directions(cam.pixel_grid()))
        misses = int((centre.index < 0).sum()) + int((hits.index < 0).sum())
        if misses:
            raise ValueError(f"scene {self.spec.name!r}, {frame_label}: {misses} rays see no "
                             f"surface; enclose the scene (e.g. a 'room' object)")
        return rgb, centre


def sample_frame(spec: SceneSpec, frame: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point-sample frame ``frame`` of ``spec`` at image points [M,2] (x, y; pixel (i, j) has its
    centre at (j + 0.5, i + 0.5)), without anti-aliasing.

    Returns colour [M,3] float64 in [0, 1] and z-depth [M] (inf where a ray sees nothing). The
    exact continuous image a stored PNG is a filtered, quantised sampling of; tests use it to
    check flow without resampling error.
    """
    if not isinstance(frame, int) or not 0 <= frame < spec.frames:
        raise ValueError(f"frame must be an integer in [0, {spec.frames - 1}], got {frame!r}")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or not np.isfinite(points).all():
        raise ValueError(f"points must be a finite [M,2] array, got shape {points.shape}")
    scene = BuiltScene(spec)
    cam = frame_cameras(spec)[frame]
    placements = scene.placements(cam.time)
    dirs = cam.directions(points)
    hits = cast(placements, cam.center, dirs)
    light = light_at(spec.light, spec.effect("lighting"), cam.time)
    return shade(hits, dirs, placements, scene.objects, scene.texture_seeds, light), hits.depth


def _scaled(c2w: np.ndarray, scene_scale: float) -> np.ndarray:
    """A camera-to-world pose with its translation in the written world units."""
    if scene_scale == 1.0:
        return c2w
    out = np.array(c2w, dtype=np.float64)
    out[:3, 3] *= scene_scale
    return out


def simulate(spec: SceneSpec, out_dir: Union[str, Path], progress: bool = True, priors: Optional[Priors] = None,
             scene_scale: float = 1.0) -> Path:
    """Render ``spec`` into ``out_dir`` (see the module docstring for the layout); returns it.

    priors: how disparity and masks are written (None: exact; `Priors.real()`: as a real capture).
    scene_scale: world units of the output (every length x scene_scale; > 0).

    The scene is built in a hidden staging directory and renamed into place when complete; an
    existing earlier output (a directory with scene.json) is replaced, any other non-empty
    directory is refused. Deterministic: the same spec gives byte-identical files.
    """
    if not isinstance(spec, SceneSpec):
        raise ValueError(f"simulate() needs a SceneSpec, got {type(spec).__name__}")
    out = Path(out_dir)
    priors = priors or Priors()
    if not (isinstance(scene_scale, (int, float)) and np.isfinite(scene_scale) and scene_scale > 0):
        raise ValueError(f"scene_scale must be a finite number > 0, got {scene_scale!r}")
    scene_scale = float(scene_scale)
    check_destination(out)
    scene = BuiltScene(spec)  # validates the object graph before any rendering
    cameras = frame_cameras(spec)
    second = vrig_cameras(spec, cameras)
    times = [cam.time for cam in cameras]
    placements = [scene.placements(t) for t in times]
    renderer = _Renderer(spec, scene)
    n = spec.frames

    staging = staging_dir(out)
    try:
        bounds = np.zeros((n, 2))
        for i in tqdm(range(n), desc=f"simulate {spec.name}", unit="frame", disable=not progress):
            stem, cam = frame_name(i, n), cameras[i]
            rgb, centre = renderer.render(cam, placements[i], f"frame {i}")
            depth = centre.depth.reshape(cam.height, cam.width) * scene_scale
            bounds[i] = depth.min() * _NEAR_FACTOR, depth.max() * _FAR_FACTOR
            write_png(staging / "images" / f"{stem}.png", to_uint8(rgb))
            write_npy(staging / "disp" / f"{stem}.npy", priors.disparity(depth, i, spec.seed))
            write_npy(staging / "gt" / "depth" / f"{stem}.npy", depth.astype(np.float32))
            dynamic = mask_png(scene.dynamic[centre.index].reshape(cam.height, cam.width))
            write_png(staging / "gt" / "motion_masks" / f"{stem}.png", dynamic)
            if priors.masks:
                write_png(staging / "motion_masks" / f"{stem}.png", dynamic)
            for j, kind in ((i + 1, "fwd"), (i - 1, "bwd")):
                if 0 <= j < n:
                    flow, occluded = scene_flow(centre, cam, cameras[j], placements[j])
                    write_npy(staging / "gt" / f"flow_{kind}" / f"{stem}.npy", flow)
                    write_png(staging / "gt" / f"occ_{kind}" / f"{stem}.png", mask_png(occluded))
            if second is not None:
                rgb2, centre2 = renderer.render(second[i], placements[i], f"vrig frame {i}")
                write_png(staging / "gt" / "vrig" / "images" / f"{stem}.png", to_uint8(rgb2))
                write_npy(staging / "gt" / "vrig" / "depth" / f"{stem}.npy",
                          (centre2.depth.reshape(cam.height, cam.width) * scene_scale).astype(np.float32))
        _write_metadata(staging, spec, scene, cameras, second, bounds, priors, scene_scale)
        publish(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out


def _camera_records(cameras: list[FrameCamera], image_dir: str, scene_scale: float) -> list[dict]:
    n = len(cameras)
    records = []
    for i, cam in enumerate(cameras):
        viewmat = np.array(cam.viewmat, dtype=np.float64)
        viewmat[:3, 3] *= scene_scale
        records.append({"frame": i, "image": f"{image_dir}/{frame_name(i, n)}.png", "time": cam.time,
                        "camera_id": cam.camera_id, "width": cam.width, "height": cam.height,
                        "K": cam.K.tolist(), "viewmat": viewmat.tolist()})
    return records


def _write_metadata(root: Path, spec: SceneSpec, scene: BuiltScene, cameras: list[FrameCamera],
                    second: Optional[list[FrameCamera]], bounds: np.ndarray, priors: Priors,
                    scene_scale: float) -> None:
    n = spec.frames
    rows = []
    for cam, (near, far) in zip(cameras, bounds):
        hwf = np.array([[cam.height], [cam.width], [cam.K[0, 0]]], dtype=np.float64)
        rows.append(np.concatenate([np.concatenate([c2w_to_llff(_scaled(cam.c2w, scene_scale)), hwf], axis=1).ravel(),
                                    [near, far]]))
    write_npy(root / "poses_bounds.npy", np.stack(rows))
    convention = ("viewmat: world-to-camera 4x4, OpenCV axes (x right, y down, z forward); "
                  "K in pixels, pixel (i, j) centred at (j + 0.5, i + 0.5)")
    write_json(root / "gt" / "cameras.json",
               {"convention": convention, "frames": _camera_records(cameras, "images", scene_scale)})
    test = [i for i in range(n) if i % LLFF_HOLD == 0]
    write_json(root / "gt" / "split.json",
               {"protocol": f"llffhold={LLFF_HOLD}: frame i is a test view iff i % {LLFF_HOLD} == 0",
                "train": [i for i in range(n) if i % LLFF_HOLD != 0], "test": test})
    if second is not None:
        write_json(root / "gt" / "vrig" / "cameras.json",
                   {"convention": convention,
                    "protocol": "vrig: train on the main camera, test on this second camera at "
                                "the same timestamps",
                    "frames": _camera_records(second, "gt/vrig/images", scene_scale)})
    write_json(root / "scene.json", {
        "simulator_version": SIMULATOR_VERSION, "name": spec.name, "seed": spec.seed,
        "frames": n, "width": spec.width, "height": spec.height,
        "effects": list(spec.effect_names), "dynamic_objects": scene.dynamic_names,
        "spec": spec.to_dict(), **_output_options(priors, scene_scale)})


def _output_options(priors: Priors, scene_scale: float) -> dict:
    """scene.json entries of the output options (absent at their defaults: exact, scale 1)."""
    out = {}
    if not priors.exact or not priors.masks:
        out["priors"] = priors.to_dict()
    if scene_scale != 1.0:
        out["scene_scale"] = scene_scale
    return out
