"""Compare a prepared dataset's cameras with known ones (synthetic clips), up to a similarity.

    errors = compare_with_truth(dataset_dir, truth_frames)

SfM recovers cameras up to a similarity transform (scale, rotation, translation). The one that
best maps the recovered cameras onto the true ones (Umeyama, least squares) is applied, then per
frame: the angle between the true and the aligned camera rotations (degrees) and the
distance between the true and the aligned centres, relative to the true trajectory's extent
(largest distance between two true centres). Frames are paired by index: dataset image
`NNNNN.png` is source frame NNNNN, i.e. `truth_frames[NNNNN]`.

The points aligned are the camera centres AND, per camera, the tips of its three axes at a
distance of one trajectory extent (each trajectory in its own scale): the centres of a short
arc or a straight path are nearly collinear, which leaves the rotation about that line
undetermined by the centres alone. `relative_rotation_error_deg_max` needs no alignment: the
largest angle between R_i R_0^T estimated and true.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..data.colmap_compat import image_cam_from_world, read_reconstruction


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R [3,3], t [3]) minimising sum |s R source_i + t - target_i|^2 (Umeyama 1991)."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    covariance = xt.T @ xs / len(source)
    u, d, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    rotation = u @ sign @ vt
    variance = (xs ** 2).sum() / len(source)
    scale = float(np.trace(np.diag(d) @ sign) / variance)
    return scale, rotation, mu_t - scale * rotation @ mu_s


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the rotation a^T b, in degrees."""
    cosine = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def _with_axis_tips(centres: np.ndarray, viewmats: Sequence[np.ndarray], length: float) -> np.ndarray:
    """Centres [N,3] followed by each camera's x, y, z axis tips at `length` from its centre."""
    tips = [c + length * v[:3, :3].T[:, k] for c, v in zip(centres, viewmats) for k in range(3)]
    return np.concatenate([centres, np.asarray(tips)])


def pose_errors(estimated_viewmats: Sequence[np.ndarray], true_viewmats: Sequence[np.ndarray]) -> dict:
    """Rotation and position errors after the best similarity (see the module docstring)."""
    est = [np.asarray(v, np.float64) for v in estimated_viewmats]
    true = [np.asarray(v, np.float64) for v in true_viewmats]
    if len(est) < 3:
        raise ValueError(f"pose_errors: need at least 3 cameras, got {len(est)}")
    centres_est = np.stack([-v[:3, :3].T @ v[:3, 3] for v in est])
    centres_true = np.stack([-v[:3, :3].T @ v[:3, 3] for v in true])
    extent = float(max(np.linalg.norm(a - b) for a in centres_true for b in centres_true))
    extent_est = float(max(np.linalg.norm(a - b) for a in centres_est for b in centres_est))
    scale, rotation, translation = umeyama(_with_axis_tips(centres_est, est, extent_est),
                                           _with_axis_tips(centres_true, true, extent))
    aligned = centres_est @ rotation.T * scale + translation
    position = np.linalg.norm(aligned - centres_true, axis=1) / max(extent, 1e-12)
    # camera-to-world rotations: true R_c2w vs (alignment R) @ estimated R_c2w
    angles = np.array([rotation_angle_deg(t[:3, :3].T, rotation @ e[:3, :3].T) for e, t in zip(est, true)])
    relative = [rotation_angle_deg(e[:3, :3] @ est[0][:3, :3].T, t[:3, :3] @ true[0][:3, :3].T)
                for e, t in zip(est, true)]
    return {"frames": len(est), "trajectory_extent": extent, "scale": scale,
            "relative_rotation_error_deg_max": float(max(relative)),
            "rotation_error_deg_mean": float(angles.mean()), "rotation_error_deg_max": float(angles.max()),
            "position_error_rel_mean": float(position.mean()), "position_error_rel_max": float(position.max())}


def compare_with_truth(dataset: Path | str, truth_frames: Sequence[dict]) -> dict:
    """`pose_errors` of `dataset/sparse/0` against per-source-frame records with a "viewmat" key
    (the simulator's gt/cameras.json "frames")."""
    model = read_reconstruction(Path(dataset) / "sparse" / "0")
    estimated, true = [], []
    for image in sorted(model.images.values(), key=lambda im: im.name):
        pose = image_cam_from_world(image)
        viewmat = np.eye(4)
        viewmat[:3, :] = pose
        estimated.append(viewmat)
        true.append(np.asarray(truth_frames[int(Path(image.name).stem)]["viewmat"], np.float64))
    return pose_errors(estimated, true)
