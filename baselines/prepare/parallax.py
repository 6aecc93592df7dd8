"""Does the camera move enough for SfM? Cheap checks on dense flow between frames.

    check = measure_parallax(images)        # before SfM: check.static skips SfM (fixed_centre.py)
    require_camera_motion(check)            # or, with --no-fixed-centre, refuses a static camera
    why = explain_failure(check)            # after a failed SfM: the likely cause, in words

For a few frame pairs spread over the clip (the first frame with later ones, and neighbours),
OpenCV SIFT matches (ratio test) give correspondences; unlike dense flow they survive the large
displacements between distant frames. Their median length says whether the camera moved at all
(the median ignores a moving object that covers less than half the view). A homography fitted with
RANSAC says whether the motion is a pure rotation (or the scene a plane): then (nearly) every
correspondence that fits the epipolar geometry (a fundamental matrix, which a moving object does
not fit) also fits the homography, and triangulation has no depth to work with.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np

from ..data.optical_flow import to_gray_u8
from .errors import PrepareError

STATIC_MEDIAN_PX = 0.5  # median flow below this on every pair: the camera does not move
ROTATION_INLIER_FRACTION = 0.95  # the homography explains this fraction of the epipolar inliers
ROTATION_PX = 1.0


@dataclass
class ParallaxCheck:
    """Per checked pair (a, b): median flow length (px) and the fraction of the fundamental
    matrix's inliers that the homography explains too."""

    pairs: list[tuple[int, int]] = field(default_factory=list)
    median_flow_px: list[float] = field(default_factory=list)
    homography_inliers: list[float] = field(default_factory=list)

    @property
    def frame_motion_px(self) -> float | None:
        """Median flow between consecutive frames (the measured neighbour pair), if measured."""
        steps = [m for (a, b), m in zip(self.pairs, self.median_flow_px) if b - a == 1]
        return steps[0] if steps else None

    @property
    def static(self) -> bool:
        return bool(self.median_flow_px) and max(self.median_flow_px) < STATIC_MEDIAN_PX

    @property
    def rotation_only(self) -> bool:
        return bool(self.homography_inliers) and min(self.homography_inliers) >= ROTATION_INLIER_FRACTION

    def as_dict(self) -> dict:
        return {"pairs": [list(p) for p in self.pairs], "median_flow_px": self.median_flow_px,
                "homography_share_of_epipolar_inliers": self.homography_inliers,
                "static": self.static, "rotation_only": self.rotation_only}


def correspondences(image_a: np.ndarray, image_b: np.ndarray, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """([M, 2], [M, 2]) SIFT matches of two images that pass Lowe's ratio test."""
    sift = cv2.SIFT_create(nfeatures=2000)
    keys_a, desc_a = sift.detectAndCompute(to_gray_u8(image_a), None)
    keys_b, desc_b = sift.detectAndCompute(to_gray_u8(image_b), None)
    if desc_a is None or desc_b is None or len(keys_a) < 2 or len(keys_b) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_a, desc_b, k=2)
    good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < ratio * n.distance]
    src = np.array([keys_a[m.queryIdx].pt for m in good], np.float64).reshape(-1, 2)
    dst = np.array([keys_b[m.trainIdx].pt for m in good], np.float64).reshape(-1, 2)
    return src, dst


def homography_share(src: np.ndarray, dst: np.ndarray) -> float:
    """Fraction of the fundamental matrix's RANSAC inliers that a RANSAC homography also fits."""
    _, in_h = cv2.findHomography(src, dst, cv2.RANSAC, ROTATION_PX)
    _, in_f = cv2.findFundamentalMat(src, dst, cv2.FM_RANSAC, ROTATION_PX, 0.999)
    if in_h is None:
        return 0.0
    if in_f is None or in_f.shape[0] != len(src):
        return float(in_h.mean())
    epipolar = in_f.ravel() > 0
    return float((in_h.ravel()[epipolar] > 0).mean()) if epipolar.any() else 0.0


def check_pairs(n: int) -> list[tuple[int, int]]:
    """The frame pairs measured: the first with a quarter, the middle and the last frame, and the
    middle's neighbour."""
    pairs = [(0, n - 1), (0, n // 2), (0, n // 4), (n // 2, min(n - 1, n // 2 + 1))]
    return sorted({p for p in pairs if p[0] != p[1]})


def measure_parallax(images: Sequence[np.ndarray]) -> ParallaxCheck:
    """Flow lengths and homography fits on `check_pairs` of `images` (uint8 BGR or grey, one size)."""
    check = ParallaxCheck()
    for a, b in check_pairs(len(images)):
        src, dst = correspondences(images[a], images[b])
        if len(src) < 8:
            continue
        check.pairs.append((a, b))
        check.median_flow_px.append(float(np.median(np.linalg.norm(dst - src, axis=1))))
        check.homography_inliers.append(homography_share(src, dst))
    return check


def static_camera_error(check: ParallaxCheck) -> PrepareError:
    """The refusal of a camera that does not move (no SfM can place the frames)."""
    return PrepareError(
        f"the camera does not move (median flow {max(check.median_flow_px, default=0.0):.2f} px between the "
        "first and last frames): structure from motion needs parallax",
        "film while walking around the scene (a static tripod shot cannot be reconstructed in 3D)")


def require_camera_motion(check: ParallaxCheck) -> None:
    """`static_camera_error` when the camera does not move."""
    if check.static:
        raise static_camera_error(check)


def explain_failure(check: ParallaxCheck, registered: int, total: int, points: int,
                    mapper: str = "incremental") -> PrepareError:
    """The error to report when mapping registered too few frames or points, with the likely cause.
    `registered` and `points` must come from the same model (the one `mapper` gave)."""
    what = f"structure from motion failed (best model, {mapper} mapper: {registered} of {total} frames registered, {points} points)"
    if check.rotation_only:
        return PrepareError(f"{what}: the camera only rotates (a homography explains "
                            f"{min(check.homography_inliers):.0%} of the motion), so depth cannot be triangulated",
                            "move the camera sideways while filming, not just turn it")
    return PrepareError(f"{what}: too few reliable matches between frames",
                        "use more frames (--fps, --max-frames), a larger --size, or footage with more texture "
                        "and slower motion")
