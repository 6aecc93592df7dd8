"""Static 3D points triangulated from KNOWN cameras with pycolmap.

SIFT features are extracted from the camera images (never inside motion masks), matched
(exhaustively for short sequences, sequentially for long ones), geometrically verified, then
triangulated with every pose and intrinsic held fixed. This is the incomplete initialisation the
ReFlow paper criticises: moving objects are excluded by design and left to densification.

pycolmap calls used (API of pycolmap >= 4.0; see `colmap_compat.py` for version notes):
`Database.open`, `extract_features` (ImageReaderOptions(camera_model, mask_path),
FeatureExtractionOptions), `Database.read_all_images/read_camera/update_camera`,
`match_exhaustive` / `match_sequential`, `Reconstruction.add_camera_with_trivial_rig`,
`Reconstruction.add_image_with_trivial_frame(image, Rigid3d)`, `triangulate_points`.
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from .cameras import Camera
from .colmap_compat import quiet_colmap_logs


@dataclass
class Triangulation:
    """Triangulated points and their evidence.

    points [P,3] world coordinates; colors [P,3] in [0,1]; errors [P] mean reprojection error
    in pixels; track_lengths [P]; observations: obs_point [M] (point index), obs_camera [M]
    (index into the cameras passed in), obs_xy [M,2] (pixel coordinates, our convention).
    """

    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    track_lengths: np.ndarray
    obs_point: np.ndarray
    obs_camera: np.ndarray
    obs_xy: np.ndarray
    num_images: int
    num_verified_pairs: int

    def __len__(self) -> int:
        return len(self.points)


def select_cameras(cameras: Sequence[Camera], max_images: int) -> list[int]:
    """Indices of up to `max_images` cameras with images, evenly spread over the sequence."""
    usable = [i for i, c in enumerate(cameras) if c.image is not None]
    if len(usable) <= max_images:
        return usable
    picks = np.linspace(0, len(usable) - 1, max_images).round().astype(int)
    return [usable[i] for i in picks]


def _write_inputs(cameras: Sequence[Camera], work: Path, mask_margin: int) -> tuple[list[str], bool]:
    """Write images (8-bit PNG) and, when any camera has a motion mask, COLMAP feature masks."""
    image_dir, mask_dir = work / "images", work / "masks"
    image_dir.mkdir()
    has_masks = any(c.mask is not None for c in cameras)
    if has_masks:
        mask_dir.mkdir()
    names = []
    kernel = np.ones((2 * mask_margin + 1, 2 * mask_margin + 1), np.uint8) if mask_margin > 0 else None
    for k, camera in enumerate(cameras):
        name = f"{k:05d}.png"
        names.append(name)
        rgb = (camera.image.detach().cpu().clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
        cv2.imwrite(str(image_dir / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if has_masks:
            # COLMAP extracts no feature where the mask is 0: black out the dynamic region, grown
            # by `mask_margin` px so descriptors straddling its border are dropped too.
            keep = np.full((camera.height, camera.width), 255, np.uint8)
            if camera.mask is not None:
                keep[camera.mask.detach().cpu().numpy() >= 0.5] = 0
                if kernel is not None:
                    keep = cv2.erode(keep, kernel)
            cv2.imwrite(str(mask_dir / f"{name}.png"), keep)
    return names, has_masks


def triangulate_static_points(cameras: Sequence[Camera], *, max_images: int = 100, mask_margin: int = 2,
                              exhaustive_up_to: int = 50, sequential_overlap: int = 10,
                              max_features: int = 8192, max_reprojection_error: float = 2.0,
                              min_track_length: int = 3, seed: int = 0, num_threads: int = 1) -> Triangulation:
    """Triangulate static scene points from `cameras` whose poses and intrinsics are fixed.

    Args:
        cameras: views with images (others are skipped); skew in K is ignored (PINHOLE model).
        max_images: evenly subsample longer sequences to this many views.
        mask_margin: pixels by which motion masks are grown before excluding features.
        exhaustive_up_to: match all pairs up to this many views, else sequential matching.
        sequential_overlap: neighbours matched per view in sequential mode.
        max_features: SIFT features per image.
        max_reprojection_error, min_track_length: filters on the triangulated points.
        seed: seeds COLMAP's RANSAC for repeatable results.
        num_threads: COLMAP threads. 1 (default) is bit-reproducible for a fixed seed; with more
            threads (-1 = all cores) the matching/verification work is scheduled across threads
            with per-thread RANSAC streams, and the point set varies between identical runs
            (500 vs 502 points seen).

    Raises whatever pycolmap raises on failure; an image set with no matches gives 0 points.
    """
    import pycolmap

    chosen = select_cameras(cameras, max_images)
    views = [cameras[i] for i in chosen]
    empty = Triangulation(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0), np.zeros(0, int),
                          np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), len(views), 0)
    if len(views) < 2:
        return empty
    pycolmap.set_random_seed(seed)
    # COLMAP's INFO/WARNING chatter is silenced; failures surface as exceptions or empty results.
    with tempfile.TemporaryDirectory(prefix="triangulate_") as tmp, quiet_colmap_logs(min_level=2):
        work = Path(tmp)
        names, has_masks = _write_inputs(views, work, mask_margin)
        database = work / "database.db"
        reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE")
        if has_masks:
            reader.mask_path = str(work / "masks")
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.sift.max_num_features = max_features
        pycolmap.extract_features(database, work / "images", image_names=names,
                                  camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                                  extraction_options=extraction)
        # The database's per-image cameras get our intrinsics, so matching, verification and
        # triangulation all use the known calibration.
        db = pycolmap.Database.open(database)
        try:
            db_images = {im.name: im for im in db.read_all_images()}
            for name, view in zip(names, views):
                camera = db.read_camera(db_images[name].camera_id)
                K = view.K.detach().cpu().double().numpy()
                camera.params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
                db.update_camera(camera)
            db_cameras = {c.camera_id: c for c in db.read_all_cameras()}
        finally:
            db.close()
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        if len(views) <= exhaustive_up_to:
            pycolmap.match_exhaustive(database, matching_options=matching)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = sequential_overlap
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing)
        db = pycolmap.Database.open(database)
        try:
            num_pairs = db.num_verified_image_pairs()
        finally:
            db.close()
        if num_pairs == 0:
            empty.num_verified_pairs = 0
            return empty

        reconstruction = pycolmap.Reconstruction()
        for camera in db_cameras.values():
            reconstruction.add_camera_with_trivial_rig(camera)
        for name, view in zip(names, views):
            db_image = db_images[name]
            viewmat = view.viewmat.detach().cpu().double().numpy()
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(viewmat[:3, :3]), viewmat[:3, 3])
            image = pycolmap.Image(name=name, camera_id=db_image.camera_id, image_id=db_image.image_id)
            reconstruction.add_image_with_trivial_frame(image, pose)
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = num_threads
        if hasattr(options, "random_seed"):
            options.random_seed = seed
        output = work / "triangulated"
        output.mkdir()
        result = pycolmap.triangulate_points(reconstruction, database, work / "images", output,
                                             clear_points=True, options=options, refine_intrinsics=False)
        return _collect(result, names, chosen, num_pairs, max_reprojection_error, min_track_length)


def _collect(reconstruction, names: list[str], chosen: list[int], num_pairs: int, max_error: float,
             min_track: int) -> Triangulation:
    index_of_name = {name: chosen[k] for k, name in enumerate(names)}
    camera_of_image = {image_id: index_of_name[image.name] for image_id, image in reconstruction.images.items()}
    points, colors, errors, lengths = [], [], [], []
    obs_point, obs_camera, obs_xy = [], [], []
    for point in reconstruction.points3D.values():
        elements = point.track.elements
        if len(elements) < min_track or not point.error <= max_error:
            continue
        k = len(points)
        points.append(point.xyz)
        colors.append(np.asarray(point.color, np.float32) / 255.0)
        errors.append(point.error)
        lengths.append(len(elements))
        for element in elements:
            obs_point.append(k)
            obs_camera.append(camera_of_image[element.image_id])
            obs_xy.append(reconstruction.images[element.image_id].points2D[element.point2D_idx].xy)
    return Triangulation(
        points=np.asarray(points, np.float32).reshape(-1, 3), colors=np.asarray(colors, np.float32).reshape(-1, 3),
        errors=np.asarray(errors, np.float64), track_lengths=np.asarray(lengths, int),
        obs_point=np.asarray(obs_point, int), obs_camera=np.asarray(obs_camera, int),
        obs_xy=np.asarray(obs_xy, np.float64).reshape(-1, 2), num_images=len(names), num_verified_pairs=num_pairs)
