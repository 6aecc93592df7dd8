"""`prepare()`: video or frame folder -> COLMAP-layout dataset, stage by stage, reusing what is done.

Stages (each skipped when its key, see `cache.py`, matches a finished run in `<out>/.prepare/`):
frames -> parallax check -> masks -> features -> matching -> mapping -> posed masks; then the
dataset and the report are written. A camera that does not move skips features, matching and
mapping, and one that only turns replaces a failed mapping: both get every frame at one centre
(`fixed_centre.py`; `--no-fixed-centre` refuses them instead). The pre-SfM masks (`--masks auto`, the default) keep movers
out of feature extraction and are the dataset's `motion_masks/`; with `--masks posed` the
dataset gets the posed masks instead (`remask.py`: re-estimated with the registered cameras); a
folder of masks is written as given. Checks that need no decoding (missing input, empty or mixed-size folder,
unreadable video, bad options, output folder owned by something else) run first.
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from .cache import StageCache, file_identity
from .dataset import MEDIAN_DEPTH, frame_times, rescale, write_dataset
from .errors import PrepareError
from .frames import extract_frames, probe_source
from .masks import MaskInfo, colmap_mask, motion_masks
from .parallax import explain_failure, measure_parallax, require_camera_motion, static_camera_error
from .report import model_statistics, summary_lines, write_report
from .sfm import (CAMERA_MODELS, PATH_JUMP_FACTOR, SfmOptions, better_model, continuous_stretch, extract_features,
                  global_map_frames, map_frames, match_frames, model_quality, read_model)

WORK_DIR = ".prepare"
MIN_REGISTERED = 3  # fewer registered frames, or fewer 3D points, is a failed reconstruction
MIN_POINTS = 20
# default frame budget: a clip of 50-90 frames is kept whole, a longer video thinned evenly so
# that masks + SfM stay within a few minutes on 2 cores at 320-480 px (the mapping grows
# faster than linearly with the frame count)
FRAME_BUDGET = 80
BEST_MODEL = "best"
GLOBAL_MODELS = "global_models"
# incremental mapping registering fewer than this fraction of the frames calls the global mapper:
# a casual clip whose incremental model split in two (a fast pan, a blurred stretch) is the case
GLOBAL_FALLBACK_FRACTION = 0.8
# --masks: "auto" writes the pre-SfM masks; "posed" re-estimates them after mapping with the
# registered cameras (remask.py). Not the default: on the six held-out DAVIS clips the posed
# masks' IoU is 0.33 against 0.31 and their precision lower (goat 0.76 -> 0.22, motocross-jump
# 0.39 -> 0.19; docs/DATASETS.md), and false positives are what seed ReFlow's dynamic points on
# the background (docs/REAL_CAPTURES.md, motocross-jump); no ReFlow run has measured them yet.
MASK_MODES = ("auto", "posed", "background", "none")
# the mapper name of a camera that does not translate (fixed_centre.py): a static or turning
# tripod shot, written with one centre for every frame instead of refused
FIXED_CENTRE = "fixed centre"
# --seed: COLMAP's random seeds are C ints (pycolmap refuses more); -1 there means "seed from the clock"
SEED_MAX = 2**31 - 1


@dataclass
class PrepareOptions:
    """Command-line options of `python -m baselines.prepare` (see `__main__.py`)."""

    source: Path
    output: Path
    fps: float | None = None
    max_frames: int | None = FRAME_BUDGET
    width: int | None = 640  # --size
    masks: str = "auto"
    sfm: SfmOptions = field(default_factory=SfmOptions)
    progress: bool = True
    # a camera that does not move, or only turns: write every frame at one centre (True) or
    # stop with the error that SfM cannot place it (False, --no-fixed-centre)
    fixed_centre: bool = True

    def validate(self) -> None:
        if self.fps is not None and not self.fps > 0:
            raise PrepareError(f"--fps {self.fps}: must be positive")
        if self.max_frames is not None and self.max_frames < 2:
            raise PrepareError(f"--max-frames {self.max_frames}: must be at least 2")
        if self.width is not None and self.width < 32:
            raise PrepareError(f"--size {self.width}: must be at least 32 pixels")
        if self.sfm.threads < 1 and self.sfm.threads != -1:
            raise PrepareError(f"--threads {self.sfm.threads}: must be at least 1, or -1 for every core")
        if self.sfm.overlap < 1:  # 0 matches no pair: SfM would fail only after extracting every frame's features
            raise PrepareError(f"--overlap {self.sfm.overlap}: must be at least 1 (frames matched ahead)")
        if not 0 <= self.sfm.seed <= SEED_MAX:  # before any frame is read: pycolmap would take -1, numpy not
            raise PrepareError(f"--seed {self.sfm.seed}: must be in [0, {SEED_MAX}]")
        if self.sfm.camera_model not in CAMERA_MODELS:
            raise PrepareError(f"--camera-model {self.sfm.camera_model}: expected one of {', '.join(CAMERA_MODELS)}")
        if self.masks not in MASK_MODES and not Path(self.masks).is_dir():
            raise PrepareError(f"--masks {self.masks}: expected {', '.join(MASK_MODES)} or a folder of mask images")
        output = Path(self.output)
        if output.exists() and (not output.is_dir() or (any(output.iterdir()) and not (output / WORK_DIR).is_dir())):
            raise PrepareError(f"output {output} exists and was not written by prepare",
                               "choose another -o folder or empty it")


def _read_frames(frame_dir: Path, names: list[str]) -> list[np.ndarray]:
    return [cv2.imread(str(frame_dir / n), cv2.IMREAD_COLOR) for n in names]


def _masks_stage(options: PrepareOptions, mode: str, cache: StageCache, key: str, names: list[str],
                 images: list[np.ndarray], frame_motion_px: float | None, work: Path) -> tuple[dict[str, np.ndarray] | None, dict, Path | None]:
    """(masks by frame name or None, mask info, COLMAP mask folder or None) for `mode` "auto",
    "none" or a folder (`motion_masks`)."""
    mask_dir, colmap_dir = work / "masks", work / "colmap_masks"
    if cache.done("masks", key):
        info = cache.extra("masks")
        if info["source"] == "none":
            return None, info, None
        masks = {n: cv2.imread(str(mask_dir / n), cv2.IMREAD_GRAYSCALE) > 0 for n in names}
        return masks, info, colmap_dir
    for folder in (mask_dir, colmap_dir):
        shutil.rmtree(folder, ignore_errors=True)
    found, info = motion_masks(images, mode, frame_motion_px, options.progress)
    masks = None if found is None else dict(zip(names, found))
    if masks is not None:
        mask_dir.mkdir(parents=True)
        colmap_dir.mkdir(parents=True)
        for name, mask in masks.items():
            cv2.imwrite(str(mask_dir / name), np.where(mask, 255, 0).astype(np.uint8))
            cv2.imwrite(str(colmap_dir / f"{name}.png"), colmap_mask(mask))
    cache.finish("masks", key, info.as_dict())
    return masks, info.as_dict(), colmap_dir if masks is not None else None


def _sfm_stages(options: PrepareOptions, cache: StageCache, masks_key: str, names: list[str],
                colmap_masks: Path | None, work: Path):
    """(chosen model or None, verified pairs, mapper info): features, matching and mapping, each
    reused when done.

    pycolmap writes every incremental model to `models/<k>`; when the largest registers fewer
    than GLOBAL_FALLBACK_FRACTION of the frames, the global mapper runs on the same database
    (`global_models/<k>`) and the better model (`sfm.better_model`) is kept as `models/best`.
    Each model is first reduced to its longest continuous camera path (`sfm.continuous_stretch`).
    Mapper info: {"used": "incremental" | "global", "incremental": [frames, error px],
    "global": [frames, error px] or None when it did not run, "path_breaks": {mapper: breaks
    found}, "off_path": the kept model's frames deregistered for lying off the path}.
    """
    database, models_dir, frame_dir = work / "database.db", work / "models", work / "frames"
    sfm = options.sfm
    features_key = cache.key(masks_key, sfm.camera_model, sfm.max_features)
    if not cache.done("features", features_key):
        database.unlink(missing_ok=True)
        extract_features(database, frame_dir, names, colmap_masks, sfm, options.progress)
        cache.finish("features", features_key)
    matches_key = cache.key(features_key, sfm.overlap, sfm.seed)
    if cache.done("matches", matches_key):
        verified = cache.extra("matches")["verified_pairs"]
    else:
        verified = match_frames(database, sfm, options.progress)
        cache.finish("matches", matches_key, {"verified_pairs": verified})
    mapping_key = cache.key(matches_key, sfm.as_dict(), GLOBAL_FALLBACK_FRACTION, PATH_JUMP_FACTOR)
    best_dir = models_dir / BEST_MODEL
    if cache.done("mapping", mapping_key) and best_dir.is_dir():
        return read_model(best_dir), verified, cache.extra("mapping")
    shutil.rmtree(models_dir, ignore_errors=True)
    shutil.rmtree(work / GLOBAL_MODELS, ignore_errors=True)
    model, off_path, breaks = continuous_stretch(map_frames(database, frame_dir, models_dir, len(names), sfm,
                                                            options.progress))
    mapper = {"used": "incremental", "incremental": list(model_quality(model)), "global": None,
              "path_breaks": {"incremental": breaks}, "off_path": off_path}
    if model_quality(model)[0] < GLOBAL_FALLBACK_FRACTION * len(names):
        other, other_off_path, breaks = continuous_stretch(
            global_map_frames(database, frame_dir, work / GLOBAL_MODELS, sfm, options.progress))
        mapper["global"] = list(model_quality(other))
        mapper["path_breaks"]["global"] = breaks
        if better_model(model, other):
            model, mapper["used"], mapper["off_path"] = other, "global", other_off_path
    if model is not None:
        best_dir.mkdir(parents=True)
        model.write(str(best_dir))
        model = read_model(best_dir)  # the model as written: what the dataset and the messages describe
    cache.finish("mapping", mapping_key, mapper)
    return model, verified, mapper


def _posed_masks_stage(options: PrepareOptions, cache: StageCache, key: str, out: Path, pre_sfm: dict,
                       frame_motion_px: float | None, work: Path) -> dict:
    """Re-estimate the written dataset's masks with its cameras (`remask.py`), reused when done;
    writes `out/motion_masks/` and returns the report's "masks" entry."""
    # imported here: `python -m baselines.prepare.remask` must not find its module already
    # imported by the package (runpy warns), and the package imports this module
    from .remask import mask_entry, posed_masks, read_posed_dataset, write_masks

    folder = work / "posed_masks"
    if cache.done("posed_masks", key) and folder.is_dir():
        names = sorted(p.name for p in (out / "images").iterdir())
        masks = [cv2.imread(str(folder / n), cv2.IMREAD_GRAYSCALE) > 0 for n in names]
        write_masks(out, names, masks)
        return cache.extra("posed_masks")
    start = time.perf_counter()
    names, frames, Ks, viewmats, views = read_posed_dataset(out)
    masks = posed_masks(frames, Ks, viewmats, views, frame_motion_px, progress=options.progress)
    write_masks(out, names, masks)
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(out / "motion_masks", folder)
    entry = mask_entry(masks, pre_sfm, time.perf_counter() - start)
    cache.finish("posed_masks", key, entry)
    return entry


def _fixed_centre_stage(options: PrepareOptions, names: list[str], images: list[np.ndarray],
                        masks: dict[str, np.ndarray] | None, mask_info: dict, work: Path, reason: str,
                        sfm_mapper: dict | None, refusal: PrepareError):
    """(model, verified pairs = 0, mapper info, masks, mask info) of `fixed_centre.py`: every
    frame at one centre. Estimated masks ("auto", "posed") are replaced by `background.py`'s,
    which the homographies make possible; a folder of masks is kept.

    `reason` ("static" or "rotation only") and the failed SfM's mapper info (None when SfM was
    skipped) go into the mapper info, whose "used" is "fixed centre". `refusal` is raised, with
    the reason, when the frame-to-frame homographies are not turns about one centre."""
    from .background import background_masks
    from .fixed_centre import fixed_centre_cameras, write_fixed_centre_model

    models_dir = work / "models"
    shutil.rmtree(models_dir, ignore_errors=True)  # an SfM model left here would be read as a competitor
    cameras = fixed_centre_cameras(names, images, masks)
    if not cameras.info.turns_about_one_centre:
        raise PrepareError(f"{refusal.message}; the frames are not turns about one centre either (median "
                           f"homography misfit {cameras.info.misfit:.1e})", refusal.hint)
    if masks is not None and options.masks in ("auto", "posed", "background"):
        start = time.perf_counter()
        found = background_masks(images, cameras.homographies)
        masks = dict(zip(names, found))
        mask_info = _background_entry(found, mask_info, time.perf_counter() - start)
    model = write_fixed_centre_model(models_dir / BEST_MODEL, names, images, cameras, masks, seed=options.sfm.seed)
    mapper = {"used": FIXED_CENTRE, "reason": reason, "fixed_centre": cameras.info.as_dict(),
              "incremental": None if sfm_mapper is None else sfm_mapper.get("incremental"),
              "global": None if sfm_mapper is None else sfm_mapper.get("global"), "off_path": []}
    return model, 0, mapper, masks, mask_info


def _background_masks_stage(out: Path, registered: list[str], images: dict[str, np.ndarray],
                            pre_sfm: dict[str, np.ndarray], pre_sfm_info: dict) -> dict:
    """`--masks background` on a moving camera: the written dataset's masks by background
    subtraction (`background.py`) along the homographies of consecutive registered frames (fitted
    off the pre-SfM masks), each frame's background from the frames within BACKGROUND_WINDOW;
    writes `out/motion_masks/` and returns the report's "masks" entry."""
    from .background import BACKGROUND_WINDOW, moving_camera_masks
    from .remask import write_masks

    start = time.perf_counter()
    found = moving_camera_masks([images[name] for name in registered], [pre_sfm[name] for name in registered])
    write_masks(out, registered, found)
    return {**_background_entry(found, pre_sfm_info, time.perf_counter() - start), "window": BACKGROUND_WINDOW}


def _background_entry(found: Sequence[np.ndarray], pre_sfm_info: dict, seconds: float) -> dict:
    """The report's "masks" entry of background-subtraction masks (`found`, True = moving), keeping
    the pre-SfM masks' coverage."""
    return {**MaskInfo("auto", [float(m.mean()) for m in found]).as_dict(), "stage": "background",
            "seconds": round(seconds, 2), "pre_sfm": {"mean_coverage": pre_sfm_info["mean_coverage"]}}


def _dropped(names: list[str], registered: set[str], models_dir: Path, off_path: Sequence[str] = ()) -> list[dict]:
    """Each unregistered frame with the reason (`off_path`: registered, then dropped off the camera path)."""
    elsewhere: dict[str, int] = {}
    for folder in sorted(p for p in models_dir.iterdir() if p.is_dir() and p.name != BEST_MODEL):
        try:
            other = read_model(folder)
        except Exception:  # a partial model folder: nothing to say about its frames
            continue
        for image in other.images.values():
            elsewhere[image.name] = int(other.num_reg_images())
    dropped = []
    for name in names:
        if name in registered:
            continue
        reason = (f"off the camera path (outside its longest stretch without a jump of over {PATH_JUMP_FACTOR:g} "
                  "median steps)" if name in off_path else
                  f"registered only in a separate smaller model ({elsewhere[name]} frames)" if name in elsewhere
                  else "not registered: too few matches with the reconstruction")
        dropped.append({"frame": name, "reason": reason})
    return dropped


def prepare(options: PrepareOptions) -> dict:
    """Run every stage (see the module docstring); returns the report (also written to disk)."""
    start = time.perf_counter()
    options.validate()
    info = probe_source(Path(options.source))
    out = Path(options.output)
    work = out / WORK_DIR
    cache = StageCache(work)
    frame_dir = work / "frames"

    frames_key = cache.key("frames", file_identity(options.source), options.width, options.fps, options.max_frames)
    if cache.done("frames", frames_key):
        names = cache.extra("frames")["names"]
    else:
        shutil.rmtree(frame_dir, ignore_errors=True)
        names = extract_frames(Path(options.source), info, frame_dir, options.width, options.fps,
                               options.max_frames, options.progress)
        cache.finish("frames", frames_key, {"names": names})
    images = _read_frames(frame_dir, names)
    parallax = measure_parallax(images)
    if not options.fixed_centre:
        require_camera_motion(parallax)

    # "posed" and "background" start from the "auto" masks (they keep movers out of SfM): the same cached stage
    pre_sfm_mode = "auto" if options.masks in ("posed", "background") else options.masks
    masks_source = pre_sfm_mode if pre_sfm_mode in MASK_MODES else file_identity(Path(pre_sfm_mode))
    masks_key = cache.key(frames_key, masks_source)
    masks, mask_info, colmap_masks = _masks_stage(options, pre_sfm_mode, cache, masks_key, names, images,
                                                   parallax.frame_motion_px, work)
    fixed_reason = None  # why every frame got one centre, when it did
    if parallax.static:  # no mapper can place frames without parallax: skip SfM
        fixed_reason = "static"
        model, verified, mapper, masks, mask_info = _fixed_centre_stage(options, names, images, masks, mask_info,
                                                                        work, "static", None,
                                                                        static_camera_error(parallax))
    else:
        model, verified, mapper = _sfm_stages(options, cache, masks_key, names, colmap_masks, work)
    registered = [] if model is None else sorted(image.name for image in model.images.values() if image.has_pose)
    points = 0 if model is None else int(model.num_points3D())
    if len(registered) < MIN_REGISTERED or points < MIN_POINTS:  # counted on the one model described
        failure = explain_failure(parallax, len(registered), len(names), points, mapper["used"])
        if not (parallax.rotation_only and options.fixed_centre):
            raise failure
        # a camera that only turns: SfM had no depth to triangulate, one centre fits every frame
        fixed_reason = "rotation only"
        model, _, mapper, masks, mask_info = _fixed_centre_stage(options, names, images, masks, mask_info, work,
                                                                 "rotation only", mapper, failure)
        registered = sorted(image.name for image in model.images.values())

    scale = rescale(model)
    times = frame_times(names)
    write_dataset(out, model, frame_dir, registered, times, masks)
    if fixed_reason and masks is not None:
        # the posed test reads depth from the cameras' parallax, which a fixed centre does not have:
        # estimated masks are the background's, a folder's are as given
        mask_info.setdefault("stage", "given")
    elif options.masks == "background":
        mask_info = _background_masks_stage(out, registered, dict(zip(names, images)), masks, mask_info)
    elif options.masks == "posed":
        posed_key = cache.key(masks_key, mapper, registered, "posed_masks")
        mask_info = _posed_masks_stage(options, cache, posed_key, out, {**mask_info, "stage": "pre-sfm"},
                                       parallax.frame_motion_px, work)
    elif masks is not None:
        mask_info = {**mask_info, "stage": "pre-sfm" if pre_sfm_mode == "auto" else "given"}
    report = {
        "source": str(options.source), "source_kind": info.kind, "source_frames": info.frame_count,
        "source_fps": info.fps, "source_size": [info.width, info.height],
        "extracted_frames": len(names), "frame_size": list(images[0].shape[1::-1]),
        **model_statistics(model),
        "registered": registered, "scale_applied": scale, "median_point_depth": MEDIAN_DEPTH,
        "dropped": _dropped(names, set(registered), work / "models", mapper.get("off_path", [])),
        "times": {n: times[n] for n in registered},
        "verified_pairs": verified, "mapper": mapper, "masks": mask_info, "parallax": parallax.as_dict(),
        "options": {"fps": options.fps, "max_frames": options.max_frames, "size": options.width,
                    "masks": options.masks, "sfm": options.sfm.as_dict()},
        "reused_stages": list(cache.reused), "wall_seconds": round(time.perf_counter() - start, 2),
        "output": str(out),
    }
    write_report(out, report)
    return report


__all__ = ["PrepareOptions", "prepare", "summary_lines"]
