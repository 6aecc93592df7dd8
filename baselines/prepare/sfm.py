"""Stage 3: cameras with pycolmap (SIFT, sequential matching, incremental mapping).

    options = SfmOptions(camera_model="SIMPLE_PINHOLE", threads=1)
    extract_features(database, image_dir, names, mask_dir, options)     # one shared camera
    match_frames(database, options)                                      # neighbours only, no loop closure
    model = map_frames(database, image_dir, model_dir, options)          # largest model, or None
    model = global_map_frames(database, image_dir, other_dir, options)   # GLOMAP on the same database

Mapping is incremental first; the pipeline runs the global mapper (pycolmap's `global_mapping`,
GLOMAP: rotation averaging then global positioning) when the incremental model leaves too many
frames out, and keeps the better of the two (`better_model`).

A video's camera moves continuously; a model may still register every frame and place some of
them far off the path (GLOMAP's global positioning does so where the frames' matches are few or
lie on a moving object the masks missed: DAVIS goat and motocross-jump, 2026-11-27, steps between
consecutive frames 200-370 times the median step). `continuous_stretch` keeps the longest run of
consecutive registered frames whose camera-centre steps stay under `PATH_JUMP_FACTOR` times the
median step and deregisters the others, before the two mappers' models are compared.

Video frames share one camera (`CameraMode.SINGLE`); pairs are matched only within `overlap`
frames of each other (sequential matching with loop detection off: no vocabulary tree needed).
Masks are COLMAP's: an image per frame in `mask_dir` named `<frame name>.png`, 0 = ignore.
The incremental mapper's initial-pair thresholds are relaxed for video (consecutive frames have
small baselines and small images have few keypoints); everything runs with a fixed seed and
`threads` threads. Progress bars: per chunk of frames for features, per stage for matching,
per registered frame for mapping.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm import tqdm

from ..data.colmap_compat import quiet_colmap_logs
from .errors import PrepareError

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "OPENCV")
# A step between consecutive frames' camera centres above this many median steps breaks the path.
# Measured on the 11 DAVIS clips prepared on 2026-11-27: smooth paths reach 1.4-9.4 median steps,
# the two broken ones 324 and 365 (13 and 22 steps above 20).
PATH_JUMP_FACTOR = 20.0
FEATURE_CHUNK = 8  # frames per extract_features call (one progress-bar step)


@dataclass(frozen=True)
class SfmOptions:
    """Knobs of the SfM stages (all recorded in the report and in the stage keys)."""

    camera_model: str = "SIMPLE_PINHOLE"
    max_features: int = 4096
    overlap: int = 10  # sequential matching: each frame with the next `overlap` frames
    init_min_tri_angle: float = 4.0  # degrees (COLMAP's 16 suits photo collections, not video)
    init_min_num_inliers: int = 50
    threads: int = 1
    seed: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


def extract_features(database: Path, image_dir: Path, names: Sequence[str], mask_dir: Path | None,
                     options: SfmOptions, progress: bool = True) -> None:
    """SIFT keypoints of `names` into `database`, all frames on ONE camera."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.threads
    extraction.sift.max_num_features = options.max_features
    chunks = [list(names[i:i + FEATURE_CHUNK]) for i in range(0, len(names), FEATURE_CHUNK)]
    with quiet_colmap_logs(), tqdm(total=len(names), desc="features", unit="frame", disable=not progress) as bar:
        for chunk in chunks:
            pycolmap.extract_features(database, image_dir, image_names=chunk, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            if reader.existing_camera_id < 0:  # later chunks join the first chunk's camera
                with pycolmap.Database.open(database) as db:
                    reader.existing_camera_id = min(c.camera_id for c in db.read_all_cameras())
            bar.update(len(chunk))


def match_frames(database: Path, options: SfmOptions, progress: bool = True) -> int:
    """Sequential matching with geometric verification; returns the number of verified pairs."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = options.overlap
    pairing.loop_detection = False
    pairing.num_threads = options.threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    with quiet_colmap_logs(), tqdm(total=1, desc="matching", unit="stage", disable=not progress) as bar:
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)
        bar.update(1)
    with pycolmap.Database.open(database) as db:
        return int(db.num_verified_image_pairs())


def _mapper_options(options: SfmOptions):
    import pycolmap

    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = options.threads
    pipeline.random_seed = options.seed
    pipeline.multiple_models = True  # the largest is kept; the others' frames are reported as dropped
    pipeline.min_model_size = 3
    pipeline.mapper.init_min_tri_angle = options.init_min_tri_angle
    pipeline.mapper.init_min_num_inliers = options.init_min_num_inliers
    pipeline.mapper.num_threads = options.threads
    pipeline.mapper.random_seed = options.seed
    pipeline.triangulation.random_seed = options.seed
    pipeline.ba_refine_principal_point = False
    return pipeline


def map_frames(database: Path, image_dir: Path, model_root: Path, total: int, options: SfmOptions,
               progress: bool = True):
    """Incremental mapping into `model_root/<k>`; returns the model with most frames, or None."""
    import pycolmap

    model_root.mkdir(parents=True, exist_ok=True)
    # level 3 (fatal only): bundle adjustment's gauge warnings on degenerate input and "Failed to
    # create any sparse model" would drown our one-line explanation
    with quiet_colmap_logs(3), tqdm(total=total, desc="mapping", unit="frame", disable=not progress) as bar:
        def next_image() -> None:
            if bar.n < bar.total:
                bar.update(1)
        try:
            models = pycolmap.incremental_mapping(database, image_dir, model_root, options=_mapper_options(options),
                                                  initial_image_pair_callback=lambda: bar.update(min(2, bar.total - bar.n)),
                                                  next_image_callback=next_image)
        except Exception as exc:  # COLMAP reports mapping failures as RuntimeError / ValueError
            raise PrepareError(f"pycolmap incremental mapping failed: {exc}",
                               "check the frames (--size, --fps) and the report") from exc
    if not models:
        return None
    return max(models.values(), key=lambda m: m.num_reg_images())


def global_map_frames(database: Path, image_dir: Path, model_root: Path, options: SfmOptions,
                      progress: bool = True):
    """Global mapping (GLOMAP) into `model_root/<k>`; returns the model with most frames, or None.

    A failure of the global mapper returns None (the incremental model stands), not an error."""
    import pycolmap

    model_root.mkdir(parents=True, exist_ok=True)
    pipeline = pycolmap.GlobalPipelineOptions()
    pipeline.num_threads = options.threads
    pipeline.random_seed = options.seed
    pipeline.min_model_size = 3
    pipeline.mapper.num_threads = options.threads
    pipeline.mapper.random_seed = options.seed
    with quiet_colmap_logs(3), tqdm(total=1, desc="global mapping", unit="stage", disable=not progress) as bar:
        try:
            models = pycolmap.global_mapping(database, image_dir, model_root, options=pipeline)
        except Exception:  # GLOMAP raises on view graphs it cannot solve: keep the incremental model
            models = {}
        bar.update(1)
    if not models:
        return None
    return max(models.values(), key=lambda m: m.num_reg_images())


def model_quality(model) -> tuple[int, float]:
    """(registered frames, mean reprojection error px) of a model; (0, inf) for None."""
    if model is None or model.num_reg_images() == 0:
        return 0, float("inf")
    return int(model.num_reg_images()), float(model.compute_mean_reprojection_error())


def better_model(first, second) -> bool:
    """True when `second` is better than `first`: more registered frames, then lower reprojection error."""
    (count_a, error_a), (count_b, error_b) = model_quality(first), model_quality(second)
    return count_b > count_a or (count_b == count_a and count_b > 0 and error_b < error_a)


def path_breaks(centers: np.ndarray, factor: float = PATH_JUMP_FACTOR) -> list[int]:
    """Indices i whose step centers[i] -> centers[i + 1] exceeds `factor` x the median step.

    Args:
        centers: [F, 3] camera centres of consecutive frames (F < 3, or a median step of 0: no breaks).
    """
    if len(centers) < 3:
        return []
    steps = np.linalg.norm(np.diff(np.asarray(centers, np.float64), axis=0), axis=1)
    median = float(np.median(steps))
    if not median > 0:
        return []
    return [int(i) for i in np.nonzero(steps > factor * median)[0]]


def continuous_stretch(model) -> tuple[object, list[str], int]:
    """(model, frames deregistered, breaks): the model reduced to its longest run of consecutive
    registered frames (by name) without a `path_breaks` break; the model is changed in place.
    None passes through as (None, [], 0)."""
    if model is None:
        return None, [], 0
    images = sorted((model.image(i) for i in model.reg_image_ids()), key=lambda image: image.name)
    centers = np.array([image.projection_center() for image in images]).reshape(-1, 3)
    breaks = path_breaks(centers)
    if not breaks:
        return model, [], 0
    bounds = [0, *[b + 1 for b in breaks], len(images)]
    start, stop = max(zip(bounds[:-1], bounds[1:]), key=lambda run: run[1] - run[0])  # first longest run
    dropped = [image for k, image in enumerate(images) if not start <= k < stop]
    for image in dropped:
        model.deregister_frame(image.frame_id)
    return model, sorted(image.name for image in dropped), len(breaks)


def read_model(model_dir: Path):
    """A reconstruction written by `map_frames` (for a re-run that reuses the mapping stage)."""
    import pycolmap

    return pycolmap.Reconstruction(str(model_dir))
