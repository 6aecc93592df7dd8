"""`build_canonical_space`: provider -> coarse-to-fine alignment -> static/dynamic clouds, cached.

Options come from ReFlowParams' `canonical_*` fields (options_from_params) or are given directly
(tests and benchmarks reach the simulator-only settings: depth_source="gt", noise, drift,
outliers, free_poses, mode="full").
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from plyfile import PlyData, PlyElement

from baselines.data import Camera, PointCloud
from baselines.fourdgs.checkpoint import atomic_write_ply

from . import cache
from .coarse_to_fine import align_sequence, unaligned
from .providers import DepthProvider, FlowProvider, PointmapProvider
from .split import dynamic_cloud, static_cloud

log = logging.getLogger(__name__)
PROVIDERS = ("auto", "depth", "flow")
STATIC_LABEL, DYNAMIC_LABEL = 0, 1


@dataclass
class CanonicalOptions:
    """Settings of the canonical space (see ReFlowParams' canonical_* flags for the user-facing ones)."""

    provider: str = "auto"  # auto (depth when every frame has disparity, else flow) | depth | flow
    align: bool = True  # False: the paper's "w/o align" (raw per-frame pointmaps, dataset cameras)
    clip_len: int = 25
    window: int = 4  # pairs at most this many frames apart inside a clip
    voxel: float = 0.01  # static voxel side as a fraction of the median depth (0 = keep every point)
    iterations: int = 300
    cache: bool = True
    mode: str = "coarse_to_fine"  # or "full" (every pair in one graph; O(N^2))
    free_poses: bool = False  # optimise camera poses too (the dataset's only anchor the gauge)
    max_side: int = 64  # alignment grid: every stride-th pixel, stride = ceil(longest side / max_side)
    shift: bool = False  # optimise a per-frame depth shift besides the scale (alignment.align_frames)
    mask_dynamic: bool = True  # pixels in the motion masks carry no weight in the alignment
    dynamic_points: int = 20_000
    depth_source: str = "disparity"  # depth provider: disparity (dataset) | gt (simulator gt/depth)
    noise: float = 0.0  # depth_source=gt only: controlled errors (providers.DepthProvider)
    drift: float = 0.0
    outliers: float = 0.0
    seed: int = 0
    device: str = "cpu"  # where the alignment runs (the plugin passes the training device; not in the cache key)


@dataclass
class CanonicalSpace:
    """static / dynamic clouds, the reference frame (train camera index or None) and the report."""

    static: PointCloud
    dynamic: PointCloud
    reference_frame: int | None
    report: dict[str, Any]

    def write_ply(self, run_dir: Path) -> tuple[Path, Path]:
        """static.ply and dynamic.ply in `run_dir` (xyz, rgb uint8, label 0 static / 1 dynamic)."""
        return (_write_cloud(self.static, Path(run_dir) / "static.ply", STATIC_LABEL),
                _write_cloud(self.dynamic, Path(run_dir) / "dynamic.ply", DYNAMIC_LABEL))


def _write_cloud(cloud: PointCloud, path: Path, label: int) -> Path:
    records = np.zeros(len(cloud), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                                          ("green", "u1"), ("blue", "u1"), ("label", "u1")])
    for k, name in enumerate("xyz"):
        records[name] = cloud.points[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        records[name] = np.clip(np.rint(cloud.colors[:, k] * 255), 0, 255)
    records["label"] = label
    return atomic_write_ply(PlyData([PlyElement.describe(records, "vertex")], byte_order="<"), path)


def options_from_params(p: Any) -> CanonicalOptions:
    """CanonicalOptions from ReFlowParams (its canonical_* fields)."""
    return CanonicalOptions(provider=p.canonical_provider, align=p.canonical_align, clip_len=p.canonical_clip_len,
                            window=p.canonical_window, voxel=p.canonical_voxel, iterations=p.canonical_iters,
                            cache=p.canonical_cache, shift=p.canonical_shift,
                            dynamic_points=p.seed_points)


def make_provider(cameras: Sequence[Camera], source_path: Path | None, options: CanonicalOptions) -> PointmapProvider:
    """The provider named by `options.provider` ("auto": depth with disparity on every frame, else flow)."""
    if options.provider not in PROVIDERS:
        raise ValueError(f"canonical_provider: unknown provider {options.provider!r} ({', '.join(PROVIDERS)})")
    cam = cameras[0]
    stride = max(1, math.ceil(max(cam.width, cam.height) / max(options.max_side, 1)))
    name = options.provider
    if name == "auto":
        name = "depth" if options.depth_source == "gt" or all(c.disparity is not None for c in cameras) else "flow"
    if name == "flow":
        return FlowProvider(cameras, stride)
    return DepthProvider(cameras, stride, options.depth_source, source_path, options.noise, options.drift,
                         options.outliers, options.seed)


def _check_masks(cameras: Sequence[Camera], masks: Sequence[np.ndarray] | None) -> list[np.ndarray] | None:
    if masks is None:
        return None
    if len(masks) != len(cameras):
        raise ValueError(f"canonical space: {len(masks)} motion masks for {len(cameras)} training cameras")
    out = []
    for cam, mask in zip(cameras, masks):
        mask = np.asarray(mask, bool)
        if mask.shape != (cam.height, cam.width):
            raise ValueError(f"canonical space: the mask of {cam.image_name} is {mask.shape}, "
                             f"the image {(cam.height, cam.width)}")
        out.append(mask)
    return out


def build_canonical_space(scene: Any, masks: Sequence[np.ndarray] | None, options: CanonicalOptions | None = None,
                          cache_dir: Path | None = None, progress: bool = False) -> CanonicalSpace:
    """The canonical space of `scene` (a SceneInfo or anything with train_cameras and source_path).

    masks: per training camera [H, W] bool (True = dynamic), or None (everything static).
    cache_dir: where the cache lives (None or options.cache False: no cache).
    """
    start = time.perf_counter()
    options = options or CanonicalOptions()
    cameras = [c.to("cpu") for c in scene.train_cameras]
    masks = _check_masks(cameras, masks)
    provider = make_provider(cameras, getattr(scene, "source_path", None), options)
    settings = {k: v for k, v in asdict(options).items() if k not in ("cache", "device")}
    key = cache.cache_key(cameras, masks, provider.key(), settings)
    folder = Path(cache_dir) if cache_dir is not None and options.cache else None
    hit = cache.load(folder, key)
    if hit is not None:
        arrays, reference, report = hit
        log.info("canonical space: read from the cache %s", cache.path_for(folder, key))
        return CanonicalSpace(PointCloud(arrays["static_points"], arrays["static_colors"]),
                              PointCloud(arrays["dynamic_points"], arrays["dynamic_colors"]), reference,
                              dict(report, cache="hit"))
    frames = sorted(range(len(cameras)), key=lambda k: (cameras[k].time, cameras[k].frame_index))
    rows, cols = provider.grid()
    weights = {n: (np.ones((len(rows), len(cols))) if masks is None or not options.mask_dynamic
                   else (~masks[n][np.ix_(rows, cols)]).astype(np.float64)) for n in frames}
    if options.align:
        states, alignment = align_sequence(provider, frames, weights, options.mode, options.clip_len, options.window,
                                           options.free_poses, options.iterations, progress, options.device,
                                           options.shift)
    else:
        states, alignment = unaligned(provider, frames)
    split_start = time.perf_counter()
    static = static_cloud(provider, states, masks, options.voxel)
    dynamic, reference = dynamic_cloud(provider, states, masks, options.dynamic_points, options.seed)
    report = {"provider": provider.key(), "frames": len(frames), "grid": [len(rows), len(cols)],
              "align": options.align, "alignment": alignment, "static_points": len(static),
              "dynamic_points": len(dynamic),
              "reference_frame": None if reference is None else cameras[reference].image_name,
              "seconds": {"alignment": alignment["seconds"], "split": time.perf_counter() - split_start,
                          "total": time.perf_counter() - start},
              "cache": "miss" if folder is not None else "off", "key": key,
              "poses": ({cameras[n].image_name: states[n].viewmat.tolist() for n in frames}
                        if options.free_poses else None)}
    cache.store(folder, key, {"static_points": static.points, "static_colors": static.colors,
                              "dynamic_points": dynamic.points, "dynamic_colors": dynamic.colors}, reference, report)
    log.info("canonical space: %d static + %d dynamic points (%s, %s)", len(static), len(dynamic), provider.name,
             alignment["mode"])
    return CanonicalSpace(static, dynamic, reference, report)
