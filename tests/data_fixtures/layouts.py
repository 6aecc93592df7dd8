"""Write a `FixtureScene` in each dataset layout, with known ground truth (our convention).

Each writer returns the ground truth the reader must recover: viewmats [N,4,4] (world->camera,
OpenCV axes) and K [3,3] at the written image size, per frame in frame order.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from .scene import FixtureScene

# LLFF camera-to-world rotation columns are [down, right, back]; OpenCV's are [right, down, fwd].
_LLFF = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    return (np.clip(rgb, 0, 1) * 255.0).round().astype(np.uint8)


def write_rgb(path: Path, rgb: np.ndarray, alpha: np.ndarray | None = None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    bgr = cv2.cvtColor(to_uint8(rgb), cv2.COLOR_RGB2BGR)
    if alpha is not None:
        bgr = np.concatenate([bgr, to_uint8(alpha)[..., None]], axis=2)
    assert cv2.imwrite(str(path), bgr)


def c2w(viewmat: np.ndarray) -> np.ndarray:
    return np.linalg.inv(viewmat)


def static_surface_points(scene: FixtureScene, count: int = 500, seed: int = 1) -> np.ndarray:
    """Points sampled on the static quads [count,3]."""
    rng = np.random.default_rng(seed)
    static = [q for q in scene.quads if not q.dynamic]
    which = rng.integers(0, len(static), count)
    s, r = rng.random(count), rng.random(count)
    return np.stack([static[k].origin + s[i] * static[k].edge_u + r[i] * static[k].edge_v
                     for i, k in enumerate(which)])


def write_ply(path: Path, points: np.ndarray, colours_u8: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    vertex = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                          ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, name in enumerate("xyz"):
        vertex[name] = points[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        vertex[name] = colours_u8[:, k]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))


def write_nvidia(scene: FixtureScene, out: Path, *, folder: str = "images", downscale: int = 1,
                 disp: bool = True, masks: bool = True, points: bool = False, blank: bool = False) -> dict:
    """DynamicNeRF/LLFF layout. Poses store H, W, focal of the full-size render; the image
    folder may hold a `downscale`d copy (like images_2)."""
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    size = (scene.width // downscale, scene.height // downscale)
    for i in range(scene.num_frames):
        frame = scene.render(i, blank=blank)
        M = c2w(scene.viewmats[i])
        pose = np.concatenate([M[:3, :3] @ _LLFF, M[:3, 3:4],
                               np.array([[scene.height], [scene.width], [scene.K[0, 0]]])], axis=1)
        rows.append(np.concatenate([pose.ravel(), [scene.near, scene.far]]))
        rgb = cv2.resize(frame.rgb, size, interpolation=cv2.INTER_AREA) if downscale > 1 else frame.rgb
        write_rgb(out / folder / f"{i:03d}.png", rgb)
        if disp:
            (out / "disp").mkdir(exist_ok=True)
            np.save(out / "disp" / f"{i:03d}.npy", (1.0 / frame.depth).astype(np.float32))
        if masks:
            (out / "motion_masks").mkdir(exist_ok=True)
            cv2.imwrite(str(out / "motion_masks" / f"{i:03d}.png"), frame.dynamic.astype(np.uint8) * 255)
    np.save(out / "poses_bounds.npy", np.stack(rows))
    if points:
        pts = static_surface_points(scene)
        write_ply(out / "points3D.ply", pts, np.full((len(pts), 3), 200, np.uint8))
    K = scene.K.copy()
    K[:2] /= downscale
    return {"viewmats": scene.viewmats.copy(), "K": K, "size": size}


def write_dnerf(scene: FixtureScene, out: Path, *, num_test: int = 2, time_scale: float = 0.7) -> dict:
    """D-NeRF/Blender layout with RGBA images; the last `num_test` frames form the test split.

    Times are written as time_scale * t (the reader divides by the largest). Alpha is a known
    pattern (0 on the left quarter, a ramp elsewhere) so compositing can be checked exactly.
    """
    out.mkdir(parents=True, exist_ok=True)
    w, h = scene.width, scene.height
    alpha = np.tile(np.linspace(0.0, 1.0, w, dtype=np.float32), (h, 1))
    alpha[:, : w // 4] = 0.0
    fov_x = 2.0 * np.arctan(w / (2.0 * scene.K[0, 0]))
    splits = {"train": range(scene.num_frames - num_test), "test": range(scene.num_frames - num_test, scene.num_frames)}
    for split, indices in splits.items():
        frames = []
        for i in indices:
            write_rgb(out / split / f"r_{i:03d}.png", scene.render(i).rgb, alpha)
            gl = c2w(scene.viewmats[i]) @ np.diag([1.0, -1.0, -1.0, 1.0])
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": float(time_scale * scene.times[i]),
                           "transform_matrix": gl.tolist()})
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov_x, "frames": frames}))
    return {"viewmats": scene.viewmats.copy(), "K": scene.K.copy(), "alpha": alpha, "size": (w, h)}


HYPER_CENTER = np.array([0.3, -0.2, 1.0])
HYPER_SCALE = 0.5


def write_hypernerf(scene: FixtureScene, out: Path, *, vrig: bool = False, points: bool = False,
                    scales: tuple[int, ...] = (1, 2)) -> dict:
    """HyperNeRF layout with rgb/{N}x folders. vrig: odd frames are a second camera (id 1) and
    form val_ids. Returns the NORMALISED ground truth ((position - center) * scale)."""
    out.mkdir(parents=True, exist_ok=True)
    ids = [f"{i:03d}" for i in range(scene.num_frames)]
    metadata, expected = {}, []
    for i, item in enumerate(ids):
        frame = scene.render(i)
        for n in scales:
            size = (scene.width // n, scene.height // n)
            write_rgb(out / "rgb" / f"{n}x" / f"{item}.png",
                      cv2.resize(frame.rgb, size, interpolation=cv2.INTER_AREA) if n > 1 else frame.rgb)
        R, centre = scene.viewmats[i][:3, :3], c2w(scene.viewmats[i])[:3, 3]
        camera = {"orientation": R.tolist(), "position": centre.tolist(), "focal_length": scene.K[0, 0],
                  "principal_point": [scene.K[0, 2], scene.K[1, 2]], "skew": 0.0, "pixel_aspect_ratio": 1.0,
                  "radial_distortion": [0.0, 0.0, 0.0], "tangential_distortion": [0.0, 0.0],
                  "image_size": [scene.width, scene.height]}
        (out / "camera").mkdir(exist_ok=True)
        (out / "camera" / f"{item}.json").write_text(json.dumps(camera))
        metadata[item] = {"warp_id": i, "appearance_id": i, "camera_id": (i % 2) if vrig else 0}
        V = np.eye(4)
        V[:3, :3] = R
        V[:3, 3] = -R @ ((centre - HYPER_CENTER) * HYPER_SCALE)
        expected.append(V)
    train_ids = [x for k, x in enumerate(ids) if not vrig or k % 2 == 0]
    val_ids = [x for k, x in enumerate(ids) if vrig and k % 2 == 1]
    (out / "dataset.json").write_text(json.dumps({"count": len(ids), "num_exemplars": len(train_ids),
                                                  "ids": ids, "train_ids": train_ids, "val_ids": val_ids}))
    (out / "metadata.json").write_text(json.dumps(metadata))
    (out / "scene.json").write_text(json.dumps({"center": HYPER_CENTER.tolist(), "scale": HYPER_SCALE,
                                                "near": scene.near * HYPER_SCALE, "far": scene.far * HYPER_SCALE}))
    raw_points = None
    if points:
        raw_points = static_surface_points(scene)
        np.save(out / "points.npy", raw_points)
    return {"viewmats": np.stack(expected), "K": scene.K.copy(), "raw_points": raw_points}


def write_colmap(scene: FixtureScene, out: Path, *, model: str = "PINHOLE", text: bool = False,
                 points: bool = True, name_offset: int = 0) -> dict:
    """COLMAP layout written with pycolmap (sparse/0 + images/). Image names are
    f"{i + name_offset:03d}.png"; the model's image ids are assigned in reverse frame order so
    readers cannot rely on id order."""
    import pycolmap

    out.mkdir(parents=True, exist_ok=True)
    reconstruction = pycolmap.Reconstruction()
    f, cx, cy = scene.K[0, 0], scene.K[0, 2], scene.K[1, 2]
    params = {"PINHOLE": [f, f, cx, cy], "SIMPLE_PINHOLE": [f, cx, cy], "SIMPLE_RADIAL": [f, cx, cy, 0.01],
              "OPENCV_FISHEYE": [f, f, cx, cy, 0, 0, 0, 0]}[model]
    camera = pycolmap.Camera(model=model, width=scene.width, height=scene.height, params=params, camera_id=1)
    reconstruction.add_camera_with_trivial_rig(camera)
    n = scene.num_frames
    for i in range(n):
        name = f"{i + name_offset:03d}.png"
        write_rgb(out / "images" / name, scene.render(i).rgb)
        V = scene.viewmats[i]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(V[:3, :3]), V[:3, 3])
        reconstruction.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=n - i), pose)
    pts = static_surface_points(scene, 200) if points else np.zeros((0, 3))
    for p in pts:
        reconstruction.add_point3D(p, pycolmap.Track(), np.array([10, 20, 30], np.uint8))
    model_dir = out / "sparse" / "0"
    model_dir.mkdir(parents=True, exist_ok=True)
    (reconstruction.write_text if text else reconstruction.write_binary)(str(model_dir))
    return {"viewmats": scene.viewmats.copy(), "K": scene.K.copy(), "points": pts}
