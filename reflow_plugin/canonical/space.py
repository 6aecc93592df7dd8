"""`build_canonical_space`: provider -> alignment -> static/dynamic clouds, cached.

Alignment, by provider:
- depth provider (monocular disparity), cameras fixed, with metric evidence (`anchors`: the
  host's sparse points, and/or the dataset's near/far bounds): scale comes first. Each frame's
  affine map in inverse depth is fitted to that evidence (reflow_plugin.disparity), then refined
  jointly (inverse.py; each sparse point with its region vote, as in the fits). `refine=False`
  stops after the per-frame fits.
- flow provider on a rig read monocularly (reflow_plugin.rig), cameras fixed: none; each frame is
  triangulated with the nearest other rig cameras (providers.py), metric as it stands.
- otherwise (flow provider, free poses, no evidence): the DUSt3R-style coarse-to-fine alignment
  (coarse_to_fine.py, alignment.py).
`align=False` is the paper's "w/o align": raw per-frame pointmaps with the dataset's cameras.

Options come from ReFlowParams' `canonical_*` fields (options_from_params) or are given directly
(tests and benchmarks reach the simulator-only settings: depth_source="gt", noise, drift,
outliers, free_poses, mode="full").
"""
from __future__ import annotations

import hashlib
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

from ..disparity import fit_frames, sparse_votes, summary
from ..params import flow_finest_from_env, flow_spread_from_env
from . import cache
from .coarse_to_fine import align_sequence, unaligned
from .inverse import align_inverse
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
    max_points: int = 20_000  # static points at most: the voxel grows until the cloud fits (0 = no limit)
    consistency: float = 0.05  # multi-view depth test of the static points (relative tolerance; 0 = off)
    iterations: int = 300
    cache: bool = True
    mode: str = "coarse_to_fine"  # or "full" (every pair in one graph; O(N^2))
    free_poses: bool = False  # optimise camera poses too (the dataset's only anchor the gauge)
    max_side: int = 64  # alignment grid: every stride-th pixel, stride = ceil(longest side / max_side)
    refine: bool = True  # inverse-depth path: joint refinement after the per-frame fits (inverse.py)
    inverse_iterations: int = 50  # Adam steps of that refinement
    mask_dynamic: bool = True  # pixels in the motion masks carry no weight in the alignment
    dynamic_points: int = 20_000
    flow_spread: int = 1  # flow provider on a sequence: partners n +- 1 .. n +- flow_spread (>1: fused_depth)
    flow_finest_scale: int | None = None  # flow provider: DIS's finest pyramid level (None: the preset's)
    depth_source: str = "disparity"  # depth provider: disparity (dataset) | gt (simulator gt/depth)
    noise: float = 0.0  # depth_source=gt only: controlled errors (providers.DepthProvider)
    drift: float = 0.0
    outliers: float = 0.0
    seed: int = 0
    device: str = "cpu"  # where the pairwise alignment runs (the plugin passes the training device; not in the
    # cache key); the anchored inverse-depth alignment always runs on the CPU (_align_inverse)


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
                            window=p.canonical_window, voxel=p.canonical_voxel, max_points=p.canonical_max_points,
                            consistency=p.canonical_consistency,
                            iterations=p.canonical_iters,
                            cache=p.canonical_cache,
                            dynamic_points=p.seed_points, flow_spread=flow_spread_from_env(),
                            flow_finest_scale=flow_finest_from_env())


def make_provider(cameras: Sequence[Camera], source_path: Path | None, options: CanonicalOptions,
                  anchors: np.ndarray | None = None) -> PointmapProvider:
    """The provider named by `options.provider` ("auto": depth with disparity on every frame, else flow);
    `anchors` ([P, 3] sparse static points or None) guide the flow provider on a rig."""
    if options.provider not in PROVIDERS:
        raise ValueError(f"canonical_provider: unknown provider {options.provider!r} ({', '.join(PROVIDERS)})")
    cam = cameras[0]
    stride = max(1, math.ceil(max(cam.width, cam.height) / max(options.max_side, 1)))
    name = options.provider
    if name == "auto":
        name = "depth" if options.depth_source == "gt" or all(c.disparity is not None for c in cameras) else "flow"
    if name == "flow":
        return FlowProvider(cameras, stride, anchors, spread=options.flow_spread,
                            finest_scale=options.flow_finest_scale)
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


def _anchored(provider: PointmapProvider, cameras: Sequence[Camera], anchors: np.ndarray | None,
              options: CanonicalOptions) -> bool:
    """Whether the inverse-depth path applies: depth provider, fixed cameras, metric evidence (sparse
    points; for the dataset's disparity the near/far bounds are enough)."""
    if not (options.align and not options.free_poses and options.mode == "coarse_to_fine"
            and isinstance(provider, DepthProvider)):
        return False
    bounds = provider.source == "disparity" and all(c.extras.get("near_far") is not None for c in cameras)
    return (anchors is not None and len(anchors) > 0) or bounds


def _metric_rig(provider: PointmapProvider, options: CanonicalOptions) -> bool:
    """Flow provider on a rig (reflow_plugin.rig) with the dataset's cameras: each frame is triangulated
    with the nearest other rig cameras, so its depth is metric as it stands; the pairwise alignment's
    edges (frames close in TIME) would be the wide-baseline matches between distant rig cameras
    (CMU Panoptic basketball at -r 4: 2.2% median depth error at the sparse points aligned, 1.9% not)."""
    return (isinstance(provider, FlowProvider) and provider.rig and not options.free_poses
            and options.mode == "coarse_to_fine")


def _align_inverse(provider: DepthProvider, cameras: Sequence[Camera], frames: list[int], weights: dict,
                   masks: Sequence[np.ndarray] | None, anchors: np.ndarray | None, options: CanonicalOptions,
                   progress: bool) -> tuple[dict, dict] | None:
    """Per-frame fits to the metric evidence, then (options.refine) the joint refinement; None when
    some frame has no fit at all (the caller falls back to the DUSt3R-style path)."""
    start = time.perf_counter()
    inverse = [provider.inverse_depth(n, full=True)[0] for n in range(len(cameras))]
    fits = fit_frames(cameras, inverse, anchors, masks)
    if not all(f.usable for f in fits):
        log.warning("canonical: %d frame(s) without any metric evidence (no sparse point, no bounds); "
                    "using the pairwise alignment instead", sum(not f.usable for f in fits))
        return None
    points = np.zeros((0, 3)) if anchors is None else anchors
    pairs = {n: sparse_votes(cameras[n], inverse[n], points, None if masks is None else masks[n]) for n in frames}
    fit_report = dict(summary(fits), frames={cameras[n].image_name: fits[n].as_dict() for n in frames})
    # On the CPU whatever the training device: a few thousand residuals per step, so on a GPU the
    # 50 steps are bound by kernel launches (embedded scene: 7.0 s on an H200 vs 2.0 s on one CPU thread)
    if options.refine:
        states, report = align_inverse(provider, frames, weights, {n: fits[n] for n in frames}, pairs,
                                       options.window, options.inverse_iterations, progress=progress,
                                       device="cpu", seed=options.seed)
    else:
        states, report = align_inverse(provider, frames, weights, {n: fits[n] for n in frames}, pairs,
                                       options.window, 0, device="cpu", seed=options.seed)
        report["mode"] = "inverse depth (per-frame fits only)"
    report["fits"] = fit_report
    report["seconds"] = time.perf_counter() - start
    return states, report


def _points_key(points: np.ndarray | None) -> str | None:
    if points is None:
        return None
    return hashlib.sha256(np.ascontiguousarray(np.asarray(points, np.float32)).tobytes()).hexdigest()[:16]


def build_canonical_space(scene: Any, masks: Sequence[np.ndarray] | None, options: CanonicalOptions | None = None,
                          cache_dir: Path | None = None, progress: bool = False,
                          anchors: np.ndarray | None = None) -> CanonicalSpace:
    """The canonical space of `scene` (a SceneInfo or anything with train_cameras and source_path).

    masks: per training camera [H, W] bool (True = dynamic), or None (everything static).
    cache_dir: where the cache lives (None or options.cache False: no cache).
    anchors: [P, 3] metric static points (the host's triangulated / dataset cloud), or None.
    """
    start = time.perf_counter()
    options = options or CanonicalOptions()
    cameras = [c.to("cpu") for c in scene.train_cameras]
    masks = _check_masks(cameras, masks)
    provider = make_provider(cameras, getattr(scene, "source_path", None), options, anchors)
    # the flow_* settings are in provider.key() where they change anything
    settings = {k: v for k, v in asdict(options).items()
                if k not in ("cache", "device", "flow_spread", "flow_finest_scale")}
    settings["anchors"] = _points_key(anchors)
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
    inverse = (_align_inverse(provider, cameras, frames, weights, masks, anchors, options, progress)
               if _anchored(provider, cameras, anchors, options) else None)
    if inverse is not None:
        states, alignment = inverse
    elif options.align and _metric_rig(provider, options):
        states, alignment = unaligned(provider, frames)
        alignment["mode"] = "none (rig: triangulated with the dataset's cameras, already metric)"
    elif options.align:
        states, alignment = align_sequence(provider, frames, weights, options.mode, options.clip_len, options.window,
                                           options.free_poses, options.iterations, progress, options.device)
    else:
        states, alignment = unaligned(provider, frames)
    split_start = time.perf_counter()
    consistency: dict[str, Any] = {}
    static = static_cloud(provider, states, masks, options.voxel, options.max_points, options.consistency,
                          consistency)
    dynamic, reference = dynamic_cloud(provider, states, masks, options.dynamic_points, options.seed)
    report = {"provider": provider.key(), "frames": len(frames), "grid": [len(rows), len(cols)],
              "align": options.align, "alignment": alignment, "static_points": len(static),
              "dynamic_points": len(dynamic), "consistency": consistency,
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
    if consistency.get("points"):
        log.info("canonical space: the multi-view depth test kept %d of %d static grid points (tolerance %g)",
                 consistency["kept"], consistency["points"], consistency["tolerance"])
    return CanonicalSpace(static, dynamic, reference, report)
