"""`initial_point_cloud`: the points a Gaussian model starts from.

Order of preference (method="auto"): the dataset's own point file ("dataset"); else static points
triangulated from the known training cameras with pycolmap ("triangulated"; motion-masked pixels
give no features); else random points inside the scene bounds ("random"), the 3DGS/4DGS random
initialisation. Triangulation that fails or yields fewer than `min_points` points falls back to
random, and the reason is logged.

The dataset's cloud is first checked against the training cameras (cloud_check.py): a placeholder
that the cameras barely see (e.g. a random cube) is skipped with a warning, and the chain goes on
to triangulation/random. `check_dataset_points=False` (train.py: `--force_dataset_points`) or
method="dataset" uses the file regardless.
"""
from __future__ import annotations

import logging

import numpy as np

from .cloud_check import check_cloud_against_cameras
from .errors import DatasetError
from .pointcloud import PointCloud, sample_colours
from .scene_info import SceneInfo
from .triangulation import triangulate_static_points

log = logging.getLogger(__name__)

METHODS = ("auto", "dataset", "triangulated", "random")


def initial_point_cloud(scene: SceneInfo, max_points: int = 200_000, seed: int = 0, method: str = "auto",
                        random_points: int = 2000, min_points: int = 100,
                        triangulation_options: dict | None = None,
                        check_dataset_points: bool = True) -> tuple[PointCloud, str]:
    """(PointCloud, source) with source in {"dataset", "triangulated", "random"}.

    Args:
        scene: a loaded scene; only its training cameras are used (test views never leak in).
        max_points: dataset and triangulated clouds larger than this are randomly subsampled.
        seed: seeds subsampling, COLMAP's RANSAC and the random initialisation.
        method: "auto" (fallback chain above) or one source, which then must succeed
            ("dataset" without a point file and failed triangulation raise `DatasetError`).
        random_points: size of a random initialisation (4DGS uses 2000 for D-NeRF).
        min_points: fewer triangulated points than this counts as a failure.
        triangulation_options: keyword arguments for `triangulate_static_points`.
        check_dataset_points: with method="auto", skip a dataset cloud the cameras barely see.
    """
    if method == "triangulate":
        method = "triangulated"
    if method not in METHODS:
        raise DatasetError(f"unknown initial point method {method!r}; expected one of {', '.join(METHODS)}")
    if method in ("auto", "dataset"):
        cloud = scene.point_cloud
        if cloud is not None and method == "auto" and check_dataset_points:
            cloud = _unless_placeholder(scene, seed)
        if cloud is not None:
            return cloud.subsample(max_points, seed), "dataset"
        if method == "dataset":
            raise DatasetError(f"{scene.source_path}: the dataset has no point file")
    if method in ("auto", "triangulated"):
        reason = None
        try:
            result = triangulate_static_points(scene.train_cameras, seed=seed, **(triangulation_options or {}))
            if len(result) >= min_points:
                log.info("initial points: %d triangulated from %d images (%d verified pairs)",
                         len(result), result.num_images, result.num_verified_pairs)
                cloud = PointCloud(result.points, result.colors)
                return cloud.subsample(max_points, seed), "triangulated"
            reason = (f"only {len(result)} points triangulated (< min_points={min_points}) from "
                      f"{result.num_images} images with {result.num_verified_pairs} verified pairs")
        except Exception as exc:  # noqa: BLE001 - any pycolmap failure (or API mismatch) means "fall back"
            reason = f"triangulation failed: {type(exc).__name__}: {exc}"
        if method == "triangulated":
            raise DatasetError(f"{scene.source_path}: {reason}")
        log.warning("initial points: %s; falling back to %d random points", reason, random_points)
    return random_point_cloud(scene, random_points, seed), "random"


def _unless_placeholder(scene: SceneInfo, seed: int) -> PointCloud | None:
    """The dataset's cloud, or None (with a warning) when the training cameras barely see it."""
    coverage = check_cloud_against_cameras(scene.point_cloud.points, scene.train_cameras, seed=seed)
    if coverage.passed:
        return scene.point_cloud
    log.warning("initial points: %s: the dataset's point file looks like a placeholder (%s); ignoring it "
                "(--force_dataset_points uses it anyway)", scene.source_path, coverage.summary())
    return None


def random_point_cloud(scene: SceneInfo, num_points: int, seed: int = 0) -> PointCloud:
    """`num_points` random points inside the scene bounds, coloured from the images where seen.

    Bounds, first available: the dataset's box (`scene_box`, e.g. D-NeRF's [-1.3, 1.3]^3);
    the training frusta between near and far (per-camera `extras["near_far"]` or the scene's
    `near_far`; depth uniform in [near, far]); else the cube of half-side `radius` around the
    mean camera centre (the 3DGS normalisation sphere's bounding cube).
    """
    if num_points < 1:
        raise DatasetError(f"random_points={num_points}: must be positive")
    rng = np.random.default_rng(seed)
    cameras = scene.train_cameras
    has_bounds = scene.near_far is not None or all("near_far" in c.extras for c in cameras)
    if scene.scene_box is not None:
        low, high = np.asarray(scene.scene_box, np.float64)
        points = rng.uniform(low, high, size=(num_points, 3))
        colours, _ = sample_colours(points, cameras)
    elif has_bounds:
        points, colours = _sample_frusta(cameras, scene.near_far, num_points, rng)
    else:
        centre = -np.asarray(scene.nerf_normalization["translate"], np.float64)
        radius = float(scene.nerf_normalization["radius"])
        points = rng.uniform(centre - radius, centre + radius, size=(num_points, 3))
        colours, _ = sample_colours(points, cameras)
    return PointCloud(points, colours)


def _sample_frusta(cameras, near_far, num_points: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform over (camera, pixel, depth in [near, far]); colour = that pixel's colour."""
    which = rng.integers(0, len(cameras), num_points)
    points = np.empty((num_points, 3))
    colours = np.full((num_points, 3), 0.5, np.float32)
    for k, camera in enumerate(cameras):
        idx = np.nonzero(which == k)[0]
        if len(idx) == 0:
            continue
        near, far = (camera.extras["near_far"].tolist() if "near_far" in camera.extras else near_far)
        u = rng.uniform(0, camera.width, len(idx))
        v = rng.uniform(0, camera.height, len(idx))
        depth = rng.uniform(near, far, len(idx))
        K = camera.K.detach().cpu().double().numpy()
        viewmat = camera.viewmat.detach().cpu().double().numpy()
        rays = np.linalg.solve(K, np.stack([u, v, np.ones_like(u)]))  # [3, n], unit z
        cam_points = (rays * depth).T
        points[idx] = (cam_points - viewmat[:3, 3]) @ viewmat[:3, :3]  # R^T (x - t)
        if camera.image is not None:
            image = camera.image.detach().cpu().numpy()
            colours[idx] = image[np.minimum(v.astype(int), camera.height - 1), np.minimum(u.astype(int), camera.width - 1)]
    return points, colours
