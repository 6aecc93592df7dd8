"""Cameras of a clip whose camera does not translate: a tripod shot, static or turning.

    cameras = fixed_centre_cameras(names, images, masks)
    model = write_fixed_centre_model(model_dir, names, images, cameras, masks)

Structure from motion needs parallax; a camera that stays put, or only turns, gives none, so no
mapper can place its frames (`parallax.py` detects the first before SfM, the second explains a
failed SfM). Such a clip is still a monocular video a 4D method can train on: every frame is seen
from one centre, and the scene is fixed up to its unknown depth. This module writes that model:

- one centre (the origin) for every frame; frame 0 looks down +z, each later frame's rotation
  chained from the homography between it and the frame before (for a pure rotation
  H = K R K^-1, so R is the rotation nearest K^-1 H K), fitted with RANSAC on SIFT matches off
  the motion masks; a pair without a homography keeps the rotation of the frame before;
- intrinsics: principal point at the image centre; the focal length under which the
  homographies are closest to rotations (a turning camera fixes it: 139.3 px found for the
  simulator's 138.6 px pan) or, for a camera that turns less than MIN_TURN_DEG, COLMAP's prior
  for an unknown camera, 1.2 x the larger side;
- an initial cloud on the sphere of radius MEDIAN_DEPTH about the centre: pixels of every frame
  (off the motion masks) pushed out along their rays, coloured by the frame.

`FixedCentreInfo.turns_about_one_centre` says whether the homographies are turns at all (a camera
moving over a plane or zooming in on a wall gives homographies too); `prepare` uses the model
only then. The homographies also give such a clip better motion masks than the pre-SfM estimator
(`background.py`), which `prepare` uses in their place.

Depth is a guess (one sphere), so views away from the centre are not constrained; the report and
the summary say so. The model is written as COLMAP text files and read back with pycolmap, so
the dataset writer and the report treat it like a mapper's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from scipy.optimize import minimize_scalar

from .dataset import MEDIAN_DEPTH
from .parallax import correspondences

PRIOR_FOCAL_FACTOR = 1.2  # COLMAP's default focal length prior: 1.2 x max(width, height)
FOCAL_RANGE = (0.3, 3.0)  # searched focal lengths, x max(width, height)
MIN_TURN_DEG = 2.0  # a camera turning less than this over the clip leaves the focal length to the prior
HOMOGRAPHY_PX = 2.0  # RANSAC threshold of the frame-to-frame homographies
MIN_MATCHES = 12  # fewer inliers than this: no homography for the pair
CLOUD_POINTS = 4000  # size of the initial cloud, spread evenly over the frames
# median over pairs of rotation_misfit above which the frames are not related by turns about one
# centre (the camera translates, e.g. over a plane, which a homography also explains): measured
# 3e-8 (simulator, static), 2-6e-6 (simulator pan, DAVIS breakdance and drift-chicane), 1.3e-2
# (DAVIS kite-surf, a camera that moves)
MAX_ROTATION_MISFIT = 1e-4


@dataclass
class FixedCentreInfo:
    """What the model assumed and found; `rotation_deg` is each frame's angle from frame 0."""

    focal_px: float
    focal_estimated: bool
    rotation_deg: list[float] = field(default_factory=list)
    pairs_without_homography: list[str] = field(default_factory=list)
    misfit: float = 0.0  # median over pairs of rotation_misfit under the focal length used

    @property
    def turns_about_one_centre(self) -> bool:
        return self.misfit <= MAX_ROTATION_MISFIT

    def as_dict(self) -> dict:
        return {"focal_px": self.focal_px, "focal_estimated": self.focal_estimated, "rotation_misfit": self.misfit,
                "max_rotation_deg": max(self.rotation_deg, default=0.0),
                "rotation_deg": [round(r, 3) for r in self.rotation_deg],
                "pairs_without_homography": self.pairs_without_homography,
                "depth": f"unknown: the initial cloud lies on a sphere of radius {MEDIAN_DEPTH:g} about the centre"}


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """[3, 3] rotation closest (Frobenius) to `matrix` (any positive scale), via SVD."""
    u, _, vt = np.linalg.svd(matrix)
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        rotation = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return rotation


def pair_homography(image_a: np.ndarray, image_b: np.ndarray, mask_a: np.ndarray | None = None,
                    mask_b: np.ndarray | None = None) -> np.ndarray | None:
    """[3, 3] homography taking frame a's pixels to frame b's, or None with too few matches.

    SIFT matches whose keypoint lies on a moving pixel (masks True) of either frame are dropped;
    the homography is fitted to the rest with RANSAC (a moving object left over is an outlier)."""
    src, dst = correspondences(image_a, image_b)
    keep = _off_mask(src, mask_a) & _off_mask(dst, mask_b)
    src, dst = src[keep], dst[keep]
    if len(src) < MIN_MATCHES:
        return None
    homography, inliers = cv2.findHomography(src, dst, cv2.RANSAC, HOMOGRAPHY_PX)
    if homography is None or int(inliers.sum()) < MIN_MATCHES:
        return None
    return homography


def _off_mask(points: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """[M] bool: the points ([M, 2] x, y in px) that do not fall on a True pixel of `mask`."""
    if mask is None or len(points) == 0:
        return np.ones(len(points), bool)
    x = np.clip(points[:, 0].astype(int), 0, mask.shape[1] - 1)
    y = np.clip(points[:, 1].astype(int), 0, mask.shape[0] - 1)
    return ~mask[y, x]


def intrinsics(focal: float, width: int, height: int) -> np.ndarray:
    """[3, 3] K with principal point at the image centre."""
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def rotation_misfit(homographies: Sequence[np.ndarray], K: np.ndarray) -> float:
    """Sum over pairs of || M - nearest rotation(M) ||^2 with M = K^-1 H K scaled to det 1: zero
    when every homography is a rotation about the centre under K."""
    total = 0.0
    inverse_K = np.linalg.inv(K)
    for homography in homographies:
        matrix = inverse_K @ homography @ K
        matrix = matrix / np.cbrt(np.linalg.det(matrix))
        total += float(np.linalg.norm(matrix - nearest_rotation(matrix)) ** 2)
    return total


def estimate_focal(homographies: Sequence[np.ndarray], width: int, height: int) -> tuple[float, bool]:
    """(focal px, True when estimated): the focal length under which the homographies are closest to
    rotations about the centre, searched over FOCAL_RANGE x max(width, height) on a log scale.

    A camera that barely turns constrains it not at all (every focal fits, and frame-to-frame
    jitter pulls the search to its bounds); then, when the best focal lies on the searched range's
    bound, or when it fits no better than half the prior's misfit, the prior (PRIOR_FOCAL_FACTOR)
    is kept. `homographies` are consecutive frames' (frame k to k + 1), their turn measured as the
    largest angle between frame 0 and a later frame under the prior."""
    prior = PRIOR_FOCAL_FACTOR * max(width, height)
    if not homographies:
        return prior, False
    turned = max(_angle_deg(r) for r in chained_rotations(homographies, intrinsics(prior, width, height)))
    if turned < MIN_TURN_DEG:
        return prior, False
    misfit = lambda log_focal: rotation_misfit(homographies, intrinsics(float(np.exp(log_focal)), width, height))
    low, high = (np.log(f * max(width, height)) for f in FOCAL_RANGE)
    grid = np.linspace(low, high, 41)
    best = int(np.argmin([misfit(g) for g in grid]))
    if best in (0, len(grid) - 1):  # no minimum inside the range: the turn does not fix the focal
        return prior, False
    refined = minimize_scalar(misfit, bounds=(grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]),
                              method="bounded", options={"xatol": 1e-4})
    if not misfit(refined.x) < 0.5 * misfit(np.log(prior)):
        return prior, False
    return float(np.exp(refined.x)), True


def _angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))


def chained_rotations(homographies: Sequence[np.ndarray | None], K: np.ndarray) -> list[np.ndarray]:
    """World->camera rotation [3, 3] per frame, frame 0 = identity, frame k + 1 = R(H_k) frame k's
    with R(H) the rotation nearest K^-1 H K; a missing homography (None) keeps the frame before's."""
    rotations = [np.eye(3)]
    inverse_K = np.linalg.inv(K)
    for homography in homographies:
        step = np.eye(3) if homography is None else nearest_rotation(inverse_K @ homography @ K)
        rotations.append(nearest_rotation(step @ rotations[-1]))
    return rotations


def sphere_cloud(images: Sequence[np.ndarray], rotations: Sequence[np.ndarray], K: np.ndarray,
                 masks: Sequence[np.ndarray | None], total: int = CLOUD_POINTS,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """([P, 3] points, [P, 3] uint8 RGB): random static pixels of every frame on the sphere of
    radius MEDIAN_DEPTH about the origin (the shared centre)."""
    rng = np.random.default_rng(seed)
    per_frame = max(1, total // len(images))
    points, colours = [], []
    inverse_K = np.linalg.inv(K)
    for image, rotation, mask in zip(images, rotations, masks):
        height, width = image.shape[:2]
        x = rng.integers(0, width, per_frame)
        y = rng.integers(0, height, per_frame)
        if mask is not None:
            keep = ~mask[y, x]
            x, y = x[keep], y[keep]
        rays = (inverse_K @ np.stack([x + 0.5, y + 0.5, np.ones(len(x))])).T  # camera frame
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        points.append(MEDIAN_DEPTH * rays @ rotation)  # R^T d for each ray (world = R^T camera)
        colours.append(image[y, x, ::-1])  # BGR -> RGB
    return np.concatenate(points), np.concatenate(colours).astype(np.uint8)


def _quaternion_wxyz(rotation: np.ndarray) -> np.ndarray:
    """COLMAP's (qw, qx, qy, qz) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


def write_text_model(model_dir: Path, names: Sequence[str], K: np.ndarray, size: tuple[int, int],
                     rotations: Sequence[np.ndarray], points: np.ndarray, colours: np.ndarray) -> None:
    """COLMAP text model (cameras.txt, images.txt, points3D.txt): one SIMPLE_PINHOLE camera, every
    frame at the origin with its rotation, points without tracks."""
    model_dir.mkdir(parents=True, exist_ok=True)
    width, height = size
    (model_dir / "cameras.txt").write_text(
        f"1 SIMPLE_PINHOLE {width} {height} {K[0, 0]:.6f} {K[0, 2]:.6f} {K[1, 2]:.6f}\n")
    lines = []
    for image_id, (name, rotation) in enumerate(zip(names, rotations), start=1):
        qw, qx, qy, qz = _quaternion_wxyz(rotation)
        lines += [f"{image_id} {qw:.12f} {qx:.12f} {qy:.12f} {qz:.12f} 0 0 0 1 {name}", ""]
    (model_dir / "images.txt").write_text("\n".join(lines) + "\n")
    (model_dir / "points3D.txt").write_text("".join(
        f"{k} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]} {c[1]} {c[2]} 0\n"
        for k, (p, c) in enumerate(zip(points, colours), start=1)))


@dataclass
class FixedCentreCameras:
    """The cameras of a fixed-centre clip: K [3, 3], world->camera rotations [3, 3] per frame, the
    frame-to-frame homographies (frame k to k + 1; None where none was found) and the report."""

    K: np.ndarray
    rotations: list[np.ndarray]
    homographies: list[np.ndarray | None]
    info: FixedCentreInfo


def fixed_centre_cameras(names: Sequence[str], images: Sequence[np.ndarray],
                         masks: dict[str, np.ndarray] | None) -> FixedCentreCameras:
    """Cameras of the frames `names` / `images` (uint8 BGR, one size), every one at the origin;
    `masks` (True = moving) keep matches on movers out of the homographies."""
    height, width = images[0].shape[:2]
    frame_masks = [None if masks is None else masks[name] for name in names]
    homographies = [pair_homography(images[k], images[k + 1], frame_masks[k], frame_masks[k + 1])
                    for k in range(len(images) - 1)]
    focal, estimated = estimate_focal([np.eye(3) if h is None else h for h in homographies], width, height)
    K = intrinsics(focal, width, height)
    rotations = chained_rotations(homographies, K)
    missing = [f"{names[k]}->{names[k + 1]}" for k, h in enumerate(homographies) if h is None]
    found = [h for h in homographies if h is not None]
    misfit = float(np.median([rotation_misfit([h], K) for h in found])) if found else 0.0
    info = FixedCentreInfo(focal, estimated, [_angle_deg(r) for r in rotations], missing, misfit)
    return FixedCentreCameras(K, rotations, homographies, info)


def write_fixed_centre_model(model_dir: Path, names: Sequence[str], images: Sequence[np.ndarray],
                             cameras: FixedCentreCameras, masks: dict[str, np.ndarray] | None, seed: int = 0):
    """Write `cameras` and the sphere cloud (`sphere_cloud`, off `masks`) as a COLMAP text model in
    `model_dir`; returns it read back as a pycolmap Reconstruction."""
    import pycolmap

    height, width = images[0].shape[:2]
    frame_masks = [None if masks is None else masks[name] for name in names]
    points, colours = sphere_cloud(images, cameras.rotations, cameras.K, frame_masks, seed=seed)
    write_text_model(model_dir, names, cameras.K, (width, height), cameras.rotations, points, colours)
    return pycolmap.Reconstruction(str(model_dir))
