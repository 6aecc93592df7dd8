"""`SceneInfo` (what a reader returns) and the pieces every reader shares to build one."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .cameras import Camera
from .errors import DatasetError, EmptySplitError
from .pointcloud import PointCloud

log = logging.getLogger(__name__)


@dataclass
class SceneInfo:
    """A loaded dataset.

    Attributes:
        train_cameras, test_cameras: views with images, ordered by frame.
        video_cameras: render-only views (image None) for a novel-time video: the first
            training camera held fixed while time sweeps [0, 1] over `num_frames` steps.
        point_cloud: points from the dataset's own files, or None (see `initial_point_cloud`).
        nerf_normalization: {"translate": np [3], "radius": float} from the training camera
            centres, as 3DGS's getNerfppNorm (radius = 1.1 x the largest centre distance).
        dataset_type: "nvidia", "dnerf", "hypernerf" or "colmap".
        source_path: the dataset folder.
        num_frames: number of distinct time steps in the whole dataset.
        near_far: scene depth range (near, far) when the dataset states one, else None.
        scene_box: [2,3] axis-aligned box (min, max) known to hold the scene, else None.
        metadata: reader-specific facts (e.g. HyperNeRF's scene center and scale, image folder).
    """

    train_cameras: list[Camera]
    test_cameras: list[Camera]
    video_cameras: list[Camera]
    point_cloud: PointCloud | None
    nerf_normalization: dict
    dataset_type: str
    source_path: Path
    num_frames: int
    near_far: tuple[float, float] | None = None
    scene_box: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)

    @property
    def cameras_extent(self) -> float:
        """3DGS's name for the normalisation radius (scales densification thresholds)."""
        return float(self.nerf_normalization["radius"])


def nerfpp_normalization(cameras: list[Camera]) -> dict:
    """{"translate": -mean centre [3] float32, "radius": 1.1 x max distance to the mean} (3DGS).

    When every camera sits at one point (a static-camera video) the radius would be 0, which
    would zero the densification thresholds downstream; it is then set to 1.0 with a warning.
    """
    if not cameras:
        raise DatasetError("no training cameras: cannot compute the scene normalisation")
    centres = np.stack([c.camera_center.detach().cpu().double().numpy() for c in cameras])
    mean = centres.mean(axis=0)
    radius = 1.1 * float(np.linalg.norm(centres - mean, axis=1).max())
    if radius < 1e-6:
        log.warning("all training cameras share one centre: using radius 1.0 for the scene extent")
        radius = 1.0
    return {"translate": (-mean).astype(np.float32), "radius": radius}


def make_video_cameras(train_cameras: list[Camera], num_frames: int) -> list[Camera]:
    """The first training camera, fixed, with time sweeping [0, 1] in `num_frames` steps."""
    base = train_cameras[0]
    times = np.linspace(0.0, 1.0, max(int(num_frames), 1))
    return [Camera(uid=i, image_name=f"video_{i:05d}", width=base.width, height=base.height,
                   K=base.K.clone(), viewmat=base.viewmat.clone(), time=float(t), image=None,
                   frame_index=i, camera_id=base.camera_id)
            for i, t in enumerate(times)]


def renumber(cameras: list[Camera]) -> list[Camera]:
    """Set each camera's uid to its position in the list (uids index their own split)."""
    for uid, camera in enumerate(cameras):
        camera.uid = uid
    return cameras


def assemble_scene(cameras: list[Camera], train_indices: list[int], test_indices: list[int], *,
                   dataset_type: str, source_path: Path, num_frames: int,
                   point_cloud: PointCloud | None = None, near_far: tuple[float, float] | None = None,
                   scene_box: np.ndarray | None = None, metadata: dict | None = None) -> SceneInfo:
    """Split `cameras` by index lists, renumber, and add normalisation and video cameras."""
    train = renumber([cameras[i] for i in train_indices])
    test = renumber([cameras[i] for i in test_indices])
    if not train:
        held = f"all {len(test)} frame(s) are test views: --no-eval trains on every frame" if test else "no frame"
        raise EmptySplitError(f"{source_path}: the training split is empty ({held})")
    scene = SceneInfo(
        train_cameras=train, test_cameras=test, video_cameras=make_video_cameras(train, num_frames),
        point_cloud=point_cloud, nerf_normalization=nerfpp_normalization(train),
        dataset_type=dataset_type, source_path=Path(source_path), num_frames=int(num_frames),
        near_far=near_far, scene_box=scene_box, metadata=dict(metadata or {}))
    log.info("%s scene %s: %d train, %d test cameras, %d frames, %s", dataset_type, source_path,
             len(train), len(test), num_frames,
             f"{len(point_cloud)} dataset points" if point_cloud is not None else "no dataset points")
    return scene


def llff_holdout(num_views: int, eval: bool, llffhold: int) -> tuple[list[int], list[int]]:
    """(train, test) indices: with `eval`, every `llffhold`-th view (0, 8, 16, ...) is a test view."""
    if not eval:
        return list(range(num_views)), []
    if llffhold < 1:
        raise DatasetError(f"llffhold={llffhold}: must be a positive integer")
    test = [i for i in range(num_views) if i % llffhold == 0]
    return [i for i in range(num_views) if i % llffhold != 0], test
