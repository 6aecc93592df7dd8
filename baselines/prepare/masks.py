"""Stage 2: motion masks, so that keypoints on moving objects stay out of SfM.

    masks, info = motion_masks(images, mode)      # mode: "auto" | "none" | a folder of masks

"auto" estimates masks WITHOUT cameras (they are what SfM is about to compute): for each frame
and its neighbours, DIS flow gives dense matches, a fundamental matrix and a homography are
fitted to them with RANSAC (the static background is the majority), and each pixel's error is
its distance from the epipolar line or the homography's prediction, whichever is smaller. The
per-pair errors are combined and cleaned by `baselines.data.motion_masks.masks_from_pair_errors`
(the same recipe as the camera-aware estimator). Like that one it cannot see motion along the
epipolar lines. The geometric masks are blobs that cover part of an object and spill past its
edges; `snap_to_edges` then runs OpenCV's GrabCut on each frame, seeded with the mask's eroded
core as sure-moving, the rest of the mask and a band around it as undecided, and everything
farther, or in the band but explained by the static geometry at least as well as the frame's
typical background pixel, as sure-static: the mask follows the object's colour boundary where
the flow does not contradict it (DAVIS clips, benchmarks/mask_quality.py and docs/DATASETS.md:
mean IoU 0.42 -> 0.47 on the five tuning clips; without the geometric guard GrabCut also grew
into similar-coloured static surroundings, bmx-trees 0.46 -> 0.37).
A folder gives one mask per frame (sorted by name; non-zero = moving), resized to
the frames. "none" disables masking.

Masks are True where a pixel MOVES. `colmap_mask` turns one into COLMAP's convention (an image
where 0 = ignore), dilated a little so that keypoints on an object's border are dropped too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from tqdm import tqdm

from ..data.image_io import IMAGE_EXTENSIONS, truncated_jpeg
from ..data.motion_masks import MotionMaskOptions, clean_mask, masks_from_pair_errors
from ..data.resolution import require_scaled_copy
from ..data.optical_flow import pixel_grid
from .errors import PrepareError
from .frames import require_name_order

RANSAC_PX = 1.0
BORDER_DILATION_PX = 3
# Pairs are chosen by camera motion, not by a fixed frame count: a fitted F between close frames
# is loose enough to absorb an object's motion, so frame a is paired with a +- s and a +- 2s where
# s frames move the background by about PAIR_MOTION_PX. On the synthetic prepare clip (orbit,
# 160x120; benchmarks/prepare_synthetic.py) against the true masks, IoU 0.61 (20 frames, s = 3)
# and 0.45 (24 frames, s = 3), versus 0.03 and 0.55 with fixed neighbours at +-2, +-4.
PAIR_MOTION_PX = 6.0
THRESHOLD, MIN_ERROR_PX = 3.0, 0.7
HOMOGRAPHY_SHARE = 0.9  # H explaining this share of F's inliers: F is degenerate, H alone judges
# GrabCut snapping (radii in px at the mask's resolution): the core kept as sure-moving, and how far
# past the mask the boundary may move. Chosen on the tuning clips of benchmarks/mask_quality.py
# (dog, libby, goat, cows, scooter-black): erode/band 2/12 -> 0.490, 3/20 -> 0.498, 1/8 -> 0.467.
SNAP_CORE_PX, SNAP_BAND_PX, SNAP_ITERATIONS = 3, 20, 3
# Band pixels whose normalised score (error / the pair's median error, median over pairs) is under
# this are sure-static for GrabCut: the flow fits the background there. Tuning mean IoU 0.469 at
# 1.0, 0.449 at 1.5 (0.498 with no guard, which grew into static surroundings on bmx-trees).
SNAP_STATIC_SCORE = 1.0


@dataclass
class MaskInfo:
    """Where the masks came from and how much of each frame they cover."""

    source: str  # "auto" | "none" | "folder:<path>"
    coverage: list[float] = field(default_factory=list)

    def as_dict(self) -> dict:
        cover = np.asarray(self.coverage or [0.0])
        return {"source": self.source, "mean_coverage": float(cover.mean()), "max_coverage": float(cover.max()),
                "coverage": [round(c, 5) for c in self.coverage]}


def uncalibrated_error(flow: np.ndarray, step: int = 4) -> np.ndarray:
    """[H, W] px: distance of q + flow(q) from the static-scene prediction of an F or H fitted
    (RANSAC) to the flow sampled every `step` pixels.

    The homography's error is used alone when it explains about as many samples as the
    fundamental matrix (inliers at least HOMOGRAPHY_SHARE of F's): the camera then mostly turns
    (or sees a plane), F is degenerate (any epipole fits), and its epipolar lines would pass
    through a moving object's pixels too, hiding it. Otherwise the smaller of the two errors.
    """
    h, w = flow.shape[:2]
    x, y = pixel_grid(h, w)
    src = np.stack([x[::step, ::step].ravel(), y[::step, ::step].ravel()], -1)
    dst = src + flow[::step, ::step].reshape(-1, 2)
    q = np.stack([x, y, np.ones_like(x)], -1).astype(np.float64)
    target = np.stack([x + flow[..., 0], y + flow[..., 1], np.ones_like(x)], -1).astype(np.float64)
    homography, h_inliers = cv2.findHomography(src, dst, cv2.RANSAC, RANSAC_PX)
    error = np.full((h, w), np.inf)
    if homography is not None:
        predicted = q @ homography.T
        predicted = predicted[..., :2] / np.clip(predicted[..., 2:3], 1e-9, None)
        error = np.linalg.norm(target[..., :2] - predicted, axis=-1)
    fundamental, f_inliers = cv2.findFundamentalMat(src, dst, cv2.FM_RANSAC, RANSAC_PX, 0.999)
    h_count = 0 if h_inliers is None or homography is None else int(h_inliers.sum())
    f_count = 0 if f_inliers is None else int(f_inliers.sum())
    if fundamental is not None and fundamental.shape == (3, 3) and h_count < HOMOGRAPHY_SHARE * f_count:
        lines = q @ fundamental.T
        norm = np.clip(np.linalg.norm(lines[..., :2], axis=-1), 1e-12, None)
        error = np.minimum(error, np.abs((lines * target).sum(-1)) / norm)
    return error.astype(np.float32)


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1,) * 2)


def snap_to_edges(image: np.ndarray, mask: np.ndarray, static: np.ndarray | None = None,
                  core_px: int = SNAP_CORE_PX, band_px: int = SNAP_BAND_PX,
                  iterations: int = SNAP_ITERATIONS) -> np.ndarray:
    """[H, W] bool: `mask` moved onto the colour boundary of what it covers in `image` ([H, W, 3]
    uint8 or [H, W] grey) by GrabCut: pixels of the mask eroded by `core_px` are sure-moving, the
    rest of the mask probably moving, a band of `band_px` around it probably static (sure-static
    where `static`, [H, W] bool, says the geometry explains the pixel), the rest sure-static.
    The result never reaches past the band nor onto `static` pixels outside the mask. A mask
    without a core (empty, or only thin parts) is returned unchanged: no colour model to learn."""
    mask = np.asarray(mask, bool)
    moving = mask.astype(np.uint8)
    core = cv2.erode(moving, _disk(core_px)) > 0
    if not core.any():
        return mask
    band = cv2.dilate(moving, _disk(band_px)) > 0
    if band.all():  # nothing sure-static: GrabCut has no background model
        return mask
    labels = np.full(mask.shape, cv2.GC_BGD, np.uint8)
    labels[band] = cv2.GC_PR_BGD
    if static is not None:
        labels[np.asarray(static, bool) & ~mask] = cv2.GC_BGD
    labels[mask] = cv2.GC_PR_FGD
    labels[core] = cv2.GC_FGD
    colour = np.asarray(image)
    if colour.ndim == 2:
        colour = cv2.cvtColor(colour, cv2.COLOR_GRAY2BGR)
    background, foreground = np.zeros((1, 65)), np.zeros((1, 65))  # GrabCut's GMM state
    cv2.grabCut(np.ascontiguousarray(colour), labels, None, background, foreground, iterations,
                cv2.GC_INIT_WITH_MASK)
    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def pair_step(frame_motion_px: float | None, count: int) -> int:
    """Frames between paired frames: about PAIR_MOTION_PX of background motion, at most count // 4."""
    if not frame_motion_px or frame_motion_px <= 0:
        return 1
    return int(np.clip(round(PAIR_MOTION_PX / frame_motion_px), 1, max(1, count // 4)))


def estimate_masks(images: Sequence[np.ndarray], frame_motion_px: float | None = None,
                   progress: bool = True) -> list[np.ndarray]:
    """Motion masks ([H, W] bool) of `images` (uint8, one size, temporal order), no cameras needed.

    `frame_motion_px`: median background motion between consecutive frames (see `pair_step`).
    """
    step = pair_step(frame_motion_px, len(images))
    options = MotionMaskOptions(offsets=(-2 * step, -step, step, 2 * step), threshold=THRESHOLD,
                                min_error_px=MIN_ERROR_PX)
    bar = tqdm(total=len(images), desc="motion masks", unit="frame", disable=not progress)
    last = [-1]

    def pair_error(a: int, b: int, flow: np.ndarray) -> np.ndarray:
        if a != last[0]:  # frames are visited in order: one tick per new frame
            bar.update(1)
            last[0] = a
        return uncalibrated_error(flow)

    masks, report = masks_from_pair_errors(images, pair_error, options, keep_scores=True)
    bar.update(bar.total - bar.n)
    bar.close()
    # edges: then the same cleaning again (GrabCut can leave specks where the colour models overlap)
    colour = [np.asarray(image) if np.asarray(image).dtype == np.uint8
              else (np.clip(np.asarray(image, np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8) for image in images]
    # score 0 is "no evidence" (flow unreliable in every pair), not "static"
    static = [(score > 0) & (score < SNAP_STATIC_SCORE) for score in report.scores]
    return [clean_mask(snap_to_edges(image, mask, guard), options)
            for image, mask, guard in zip(colour, masks, static)]


def read_mask_folder(folder: Path, count: int, size: tuple[int, int]) -> list[np.ndarray]:
    """`count` masks from `folder` (sorted by name, non-zero = moving), resized to `size` (W, H)."""
    if not folder.is_dir():
        raise PrepareError(f"--masks {folder}: not a folder (expected auto, none or a folder of mask images)")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if len(files) != count:
        raise PrepareError(f"--masks {folder} holds {len(files)} mask images but {count} frames were extracted",
                           "give one mask per kept frame (same order), or use --masks auto")
    require_name_order(files, "the masks of --masks", "so that they sort as the frames do")
    masks = []
    for path in files:
        if truncated_jpeg(path):  # OpenCV would decode its missing rows as flat grey (a half-moving frame)
            raise PrepareError(f"mask {path} is truncated (its JPEG data ends early)", "re-copy or re-export that file")
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise PrepareError(f"cannot read mask {path}")
        try:  # train.py's rule: another resolution is fine, another shape (transposed, cropped) is not
            require_scaled_copy(path, "mask", (mask.shape[1], mask.shape[0]), size)
        except ValueError as err:
            raise PrepareError(str(err), "give masks of the frames' aspect ratio, or use --masks auto") from None
        masks.append(cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST) > 0)
    return masks


def motion_masks(images: Sequence[np.ndarray], mode: str, frame_motion_px: float | None = None,
                 progress: bool = True) -> tuple[list[np.ndarray] | None, MaskInfo]:
    """(masks or None, info) for `mode` "auto", "none" or a folder path."""
    if mode == "none":
        return None, MaskInfo("none")
    if mode == "auto":
        masks = estimate_masks(images, frame_motion_px, progress)
        source = "auto"
    else:
        height, width = images[0].shape[:2]
        masks = read_mask_folder(Path(mode), len(images), (width, height))
        source = f"folder:{mode}"
    return masks, MaskInfo(source, [float(m.mean()) for m in masks])


def colmap_mask(mask: np.ndarray) -> np.ndarray:
    """uint8 image for COLMAP's ImageReaderOptions.mask_path: 0 on (dilated) moving pixels, 255 elsewhere."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * BORDER_DILATION_PX + 1,) * 2)
    moving = cv2.dilate(mask.astype(np.uint8), kernel) > 0
    return np.where(moving, 0, 255).astype(np.uint8)
