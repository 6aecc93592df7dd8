"""Motion masks of a fixed-centre clip by background subtraction (`fixed_centre.py`'s homographies).

    masks = background_masks(images, homographies)

A camera that does not translate sees the static scene through a homography between any two
frames, so the static scene of frame k can be rebuilt from the other frames: each of up to
BACKGROUND_FRAMES frames spread over the clip is warped into frame k's view by the chained
frame-to-frame homographies, and their per-pixel median is the background (a mover that never
stays at one place for half of those frames drops out of it). A pixel moves where its colour
differs from that background by more than max(MIN_DIFFERENCE, NOISE_FACTOR x the frame's
median difference); the masks are then opened, closed and stripped of small components.

The pre-SfM estimator (`masks.py`) judges flow against an epipolar or homography fit of nearby
frames; with a camera that barely moves it picks pairs a few frames apart, whose flow misses a
fast mover and flags small motions. Against the true masks (pixels pooled over the clip;
constants set before measuring, not tuned; 2026-11-28): the simulator's static clip 0.76 -> 0.94
IoU, its 30-degree pan 0.66 -> 0.86, DAVIS breakdance 0.12 -> 0.39 and drift-chicane 0.05 -> 0.22
(the crowd behind the dancer and the tyre smoke move too, and are not annotated). A mover that
stays in one place for most of the clip becomes background: such clips keep few true positives.

`moving_camera_masks` applies the same test to a camera that moves (`--masks background`), each
frame against the frames within BACKGROUND_WINDOW of it, where a homography still aligns a far
background. On the 11 DAVIS clips SfM registers it finds a subject the camera follows
(scooter-black 0.12 -> 0.57) and loses slow ones (dog 0.70 -> 0.39): mean 0.31 against the
pre-SfM masks' 0.34, so it is opt-in (docs/DATASETS.md).
"""
from __future__ import annotations

import warnings
from typing import Sequence

import cv2
import numpy as np

from ..data.motion_masks import MotionMaskOptions, clean_mask
from .fixed_centre import pair_homography

BACKGROUND_FRAMES = 21  # frames whose median is each frame's background, spread over the clip
BACKGROUND_WINDOW = 10  # a moving camera: the frames within this many of frame k (set before measuring)
MIN_DIFFERENCE = 30.0  # RGB distance (8-bit units) below which a pixel is never moving
NOISE_FACTOR = 4.0  # x the frame's median distance to its background (sensor noise, small misfits)
CLEANING = MotionMaskOptions(open_px=1, close_px=3, min_area=0.001)


def chained_homographies(homographies: Sequence[np.ndarray | None]) -> list[np.ndarray]:
    """[3, 3] homography from frame 0 to each frame (frame k to k + 1 given; None = identity)."""
    chained = [np.eye(3)]
    for homography in homographies:
        chained.append((np.eye(3) if homography is None else homography) @ chained[-1])
    return chained


def background_frames(k: int, total: int, window: int | None, count: int = BACKGROUND_FRAMES) -> list[int]:
    """The frames whose median is frame k's background: up to `count` others spread over the clip
    (`window` None: a fixed centre, where every frame sees the scene the same way), or the frames
    within `window` of k (a moving camera: a homography aligns only nearby frames' backgrounds)."""
    if window is None:
        return sorted(set(np.linspace(0, total - 1, count + 1).round().astype(int)) - {k})[:count]
    near = [j for j in range(max(0, k - window), min(total, k + window + 1)) if j != k]
    return sorted(near, key=lambda j: abs(j - k))[:count]


def background(images: Sequence[np.ndarray], from_first: Sequence[np.ndarray], k: int,
               others: Sequence[int]) -> np.ndarray:
    """[H, W, 3] float32 background of frame k: the per-pixel median of the frames `others`
    warped into its view (NaN where none of them sees the pixel)."""
    height, width = images[k].shape[:2]
    stack = []
    for j in others:
        into_k = from_first[k] @ np.linalg.inv(from_first[j])
        stack.append(cv2.warpPerspective(images[j].astype(np.float32), into_k, (width, height),
                                         flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                         borderValue=(np.nan,) * 3))
    with warnings.catch_warnings():  # pixels no other frame sees: NaN, by design
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.stack(stack), axis=0)


def background_masks(images: Sequence[np.ndarray], homographies: Sequence[np.ndarray | None],
                     window: int | None = None) -> list[np.ndarray]:
    """[H, W] bool per frame (True = moving) of `images` (uint8, one size, at least 2) whose
    consecutive frames are related by `homographies` (frame k to k + 1; None = identity);
    `window` as in `background_frames`."""
    from_first = chained_homographies(homographies)
    masks = []
    for k, image in enumerate(images):
        others = background_frames(k, len(images), window)
        distance = np.linalg.norm(image.astype(np.float32) - background(images, from_first, k, others), axis=2)
        seen = np.isfinite(distance)
        if not seen.any():
            masks.append(np.zeros(distance.shape, bool))
            continue
        threshold = max(MIN_DIFFERENCE, NOISE_FACTOR * float(np.median(distance[seen])))
        masks.append(clean_mask(seen & (np.nan_to_num(distance) > threshold), CLEANING))
    return masks


def moving_camera_masks(frames: Sequence[np.ndarray], pre_sfm: Sequence[np.ndarray | None],
                        window: int = BACKGROUND_WINDOW) -> list[np.ndarray]:
    """`background_masks` of consecutive frames of a moving camera (uint8 BGR, one size): the
    homography of each neighbouring pair is fitted off its pre-SfM masks (True = moving), and each
    frame's background comes from the frames within `window` of it, where a homography still
    aligns the background (a far scene, or a camera that mostly turns)."""
    homographies = [pair_homography(frames[k], frames[k + 1], pre_sfm[k], pre_sfm[k + 1])
                    for k in range(len(frames) - 1)]
    return background_masks(frames, homographies, window=window)
