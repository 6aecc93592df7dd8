"""Pointmap providers: pairwise pointmaps with confidence, the input of the global alignment.

    provider = make_provider(cameras, source_path, options)
    depth, conf = provider.depth(n)           # [h, w] z-depth of frame n (unknown scale/shift), [h, w] >= 0
    pair = provider.pair(i, j)                # X_ii, X_ji [h, w, 3] in camera i's frame, C_ii, C_ji [h, w]

Every array lives on the provider's pixel grid (every `stride` pixels, geometry.grid); `full=True`
asks for full resolution (used for the reference frame's dynamic points).

Providers:
    depth  the dataset's disparity (`disp/*.npy`, loaded as Camera.disparity): depth = 1 / disparity,
           `inverse_depth` the disparity itself. Real captures ship monocular disparity of unknown
           per-frame scale and shift IN INVERSE DEPTH; canonical/inverse.py fits and aligns it
           there (the DUSt3R-style alignment's depth scale/shift cannot represent it). `depth_source="gt"` reads the
           simulator's `gt/depth/*.npy` instead, with controlled errors for tests: per-frame scale
           drift exp(drift * N(0, 1)), multiplicative noise (1 + noise * N(0, 1)) per pixel, a
           fraction `outliers` of pixels scaled by U(0.5, 2). A pair (i, j) is built like a
           learned pair model's output: both pointmaps at frame i's (unknown) scale, frame j's
           points moved into camera i by the dataset's relative pose.
    flow   two-view triangulation of OpenCV DIS optical flow with the known cameras; confidence =
           forward-backward consistency exp(-|f + b|^2 / 2) x min(1, triangulation angle / 2 deg).
           Needs a moving camera (no parallax, no depth: zero confidence). A frame is triangulated
           with its two time neighbours, except on a WIDE RIG read monocularly (reflow_plugin.rig:
           camera poses recur, consecutive frames tens of degrees apart): there a frame pairs
           with the two nearest OTHER camera poses (smallest angle between the viewing directions;
           of each pose the frame nearest in time), and, given the host's sparse points
           (`anchors`), DIS starts from the flow those points' depth implies for the static scene
           (`guide_flow`), which DIS's pyramid does not find from zero at such angles. CMU Panoptic
           basketball at -r 4 (benchmarks/rig_pairs.py; sparse points the guide did NOT read):
           median relative depth error 1.5%, the guide alone 5.8%; the time neighbours from zero
           left 12 of 23 pairs without a confident pixel there and 34% error on the rest.
           A/B switches (defaults unchanged until measured in training): `spread` k > 1 fuses
           every frame within k of a sequence (`fused_depth`; REFLOW4DGS_FLOW_SPREAD), and
           `finest_scale` sets DIS's finest pyramid level (the preset's is 1, half resolution;
           REFLOW4DGS_FLOW_FINEST). DAVIS at 160x90 (benchmarks/canonical_flow.py): the time
           neighbours leave 0 of 11 clips within the check's 2%, k = 4 at full resolution without
           the alignment 3.

A learned model (DUSt3R, MonST3R) plugs in by subclassing PointmapProvider: `pair` returns the
network's (X_i^i, X_j^i, C_i^i, C_j^i) resampled to the grid and `depth(n)` the z channel of
X_n^n from any pair containing n. We ship none (no weights download).
"""
from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from baselines.data import Camera

from ..rig import pose_groups, viewing_angle_deg, wide_rig
from .geometry import backproject, grid, relative, to_camera, to_world

MIN_ANGLE_DEG = 2.0
FUSED_AGREEMENT = 0.05  # fused depth: relative spread of the partners' inverse depths at confidence 1/e
FUSED_MIN_PARALLAX_PX = 1.0  # fused depth: full confidence from this parallax (px) of the widest partner
FUSED_SATURATION_PX = 2.0  # fused depth: a partner's weight stops growing at this parallax (px)
GUIDE_SOFTENING = 0.05  # guide_depth: the inverse-distance weights' softening, a fraction of the image width
GUIDE_CHUNK = 1 << 22  # guide_depth: pixel x point weights computed at once


@dataclass
class PairPrediction:
    """Pointmaps of a pair (i, j), both in camera i's frame, on the provider's grid.

    X_ii: [h, w, 3] frame i's pixels. X_ji: [h, w, 3] frame j's pixels. C_ii, C_ji: [h, w] >= 0
    (0 = no evidence: non-finite points always get 0).
    """

    X_ii: np.ndarray
    X_ji: np.ndarray
    C_ii: np.ndarray
    C_ji: np.ndarray

    def sanitized(self) -> "PairPrediction":
        """Non-finite points get confidence 0 and value 0; negative or NaN confidences become 0."""
        out = []
        for X, C in ((self.X_ii, self.C_ii), (self.X_ji, self.C_ji)):
            C = np.nan_to_num(np.asarray(C, np.float64), nan=0.0, posinf=0.0, neginf=0.0).clip(min=0)
            ok = np.isfinite(X).all(-1)
            out += [np.where(ok[..., None], X, 0.0), np.where(ok, C, 0.0)]
        return PairPrediction(out[0], out[2], out[1], out[3])


def _np(tensor) -> np.ndarray:
    return tensor.detach().cpu().double().numpy()


class PointmapProvider(ABC):
    """Pairwise pointmaps for the training cameras (indices into `cameras`)."""

    name = "provider"

    def __init__(self, cameras: Sequence[Camera], stride: int = 1) -> None:
        self.cameras = list(cameras)
        self.stride = int(stride)
        self.K = [_np(c.K) for c in self.cameras]
        self.viewmats = [_np(c.viewmat) for c in self.cameras]

    def grid(self, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        cam = self.cameras[0]
        return grid(cam.height, cam.width, 1 if full else self.stride)

    def colours(self, n: int, full: bool = False) -> np.ndarray:
        """[h, w, 3] colours of frame n on the grid."""
        rows, cols = self.grid(full)
        return self.cameras[n].image.detach().cpu().numpy()[np.ix_(rows, cols)]

    @abstractmethod
    def depth(self, n: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(z-depth [h, w] of frame n, up to the provider's scale/shift; confidence [h, w])."""

    @abstractmethod
    def pair(self, i: int, j: int) -> PairPrediction:
        """Pointmaps of frames i and j in camera i's frame."""

    def inverse_depth(self, n: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(inverse depth [h, w] of frame n up to the provider's affine map, confidence [h, w]);
        NaN where the depth is not positive. Monocular disparity is affine in this quantity."""
        depth, conf = self.depth(n, full)
        depth = np.asarray(depth, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(depth > 0, 1.0 / depth, np.nan), conf

    def key(self) -> str:
        """Everything the provider's output depends on besides the cameras (for the cache)."""
        return f"{self.name}|stride={self.stride}"


class DepthProvider(PointmapProvider):
    """Pointmaps from per-frame depth (dataset disparity, or simulator ground truth with errors)."""

    name = "depth"

    def __init__(self, cameras: Sequence[Camera], stride: int = 1, source: str = "disparity",
                 source_path: Path | None = None, noise: float = 0.0, drift: float = 0.0,
                 outliers: float = 0.0, seed: int = 0) -> None:
        super().__init__(cameras, stride)
        if source not in ("disparity", "gt"):
            raise ValueError(f"depth provider: unknown depth source {source!r} (disparity or gt)")
        self.source, self.source_path = source, None if source_path is None else Path(source_path)
        self.noise, self.drift, self.outliers, self.seed = noise, drift, outliers, seed
        rng = np.random.default_rng(seed)
        self.scales = np.exp(drift * rng.standard_normal(len(self.cameras)))  # [N] per-frame scale drift
        self._cache: dict[int, np.ndarray] = {}
        if source == "disparity":
            missing = [c.image_name for c in self.cameras if c.disparity is None]
            if missing:
                raise ValueError(f"depth provider: no disparity (disp/*.npy) for {len(missing)} frames, "
                                 f"e.g. {missing[0]}; use canonical_provider=flow")

    def key(self) -> str:
        return (f"{super().key()}|{self.source}|noise={self.noise}|drift={self.drift}|"
                f"outliers={self.outliers}|seed={self.seed}")

    def _clean(self, n: int) -> np.ndarray:
        """[H, W] depth at full resolution as stored (NaN where the disparity is not positive)."""
        if n in self._cache:
            return self._cache[n]
        cam = self.cameras[n]
        if self.source == "gt":
            path = (self.source_path or Path(".")) / "gt" / "depth" / f"{cam.image_name}.npy"
            if not path.is_file():
                raise ValueError(f"depth provider: {path} not found (depth_source=gt needs a simulator scene)")
            depth = np.load(path).astype(np.float64)
            if depth.shape != (cam.height, cam.width):
                depth = cv2.resize(depth, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
        else:
            disparity = cam.disparity.detach().cpu().double().numpy()
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = np.where(disparity > 1e-8, 1.0 / disparity, np.nan)
        self._cache[n] = depth
        return depth

    def _sampled(self, n: int, full: bool, *tag: int) -> np.ndarray:
        """Frame n's depth on the grid with the configured errors (scale drift excluded); every
        call site (`tag`: the frame itself, or a pair) draws its own noise, as a network would."""
        rows, cols = self.grid(full)
        depth = self._clean(n)[np.ix_(rows, cols)]
        rng = np.random.default_rng((self.seed, n, *tag))
        if self.noise > 0:
            depth = depth * np.clip(1 + self.noise * rng.standard_normal(depth.shape), 0.2, None)
        if self.outliers > 0:
            bad = rng.random(depth.shape) < self.outliers
            depth = np.where(bad, depth * rng.uniform(0.5, 2.0, depth.shape), depth)
        return depth

    def depth(self, n: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        d = self.scales[n] * self._sampled(n, full, int(full))
        return d, (np.isfinite(d) & (d > 0)).astype(np.float64)

    def inverse_depth(self, n: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The dataset's disparity as stored (any sign: its affine map decides where depth is
        positive), or 1 / depth of the gt source with its errors."""
        if self.source == "gt":
            return super().inverse_depth(n, full)
        rows, cols = self.grid(full)
        d = self.cameras[n].disparity.detach().cpu().double().numpy()[np.ix_(rows, cols)] / self.scales[n]
        return d, np.isfinite(d).astype(np.float64)

    def pair(self, i: int, j: int) -> PairPrediction:
        rows, cols = self.grid()
        X_ii = backproject(self._sampled(i, False, i, j, 2), self.K[i], rows, cols)
        X_jj = backproject(self._sampled(j, False, i, j, 3), self.K[j], rows, cols)
        T = relative(self.viewmats[i], self.viewmats[j])
        X_ji = X_jj @ T[:3, :3].T + T[:3, 3]
        s = self.scales[i]
        conf = [(np.isfinite(X).all(-1) & (X[..., 2] > 0)).astype(np.float64) for X in (X_ii, X_jj)]
        return PairPrediction(s * X_ii, s * X_ji, conf[0], conf[1]).sanitized()


def _grey(camera: Camera) -> np.ndarray:
    image = camera.image.detach().cpu().numpy()
    return cv2.cvtColor(np.clip(image * 255, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def guide_depth(points: np.ndarray, K: np.ndarray, viewmat: np.ndarray, height: int, width: int) -> np.ndarray | None:
    """[H, W] z-depth of camera (K, viewmat) interpolated from world points [P, 3] (inverse distance
    weighting in inverse depth over the points in front of the camera that project within half an
    image of it), or None with fewer than 3 such points."""
    cam = to_camera(np.asarray(points, np.float64), viewmat)
    cam = cam[cam[:, 2] > 1e-6]
    uv = cam @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    near = ((uv[:, 0] > -width / 2) & (uv[:, 0] < 1.5 * width) & (uv[:, 1] > -height / 2)
            & (uv[:, 1] < 1.5 * height))
    if near.sum() < 3:
        return None
    uv, inverse = uv[near], 1.0 / cam[near, 2]
    xs = np.arange(width) + 0.5
    out = np.empty((height, width))
    step = max(1, GUIDE_CHUNK // (width * len(uv)))  # rows per block: [rows, W, P] weights stay small
    for top in range(0, height, step):
        ys = np.arange(top, min(height, top + step))[:, None, None] + 0.5
        weights = 1.0 / ((xs[None, :, None] - uv[:, 0]) ** 2 + (ys - uv[:, 1]) ** 2 + (GUIDE_SOFTENING * width) ** 2)
        out[top:top + len(weights)] = weights.sum(-1) / (weights @ inverse)
    return out


class FlowProvider(PointmapProvider):
    """Pointmaps by triangulating DIS optical flow between two views with known cameras.

    anchors: [P, 3] world points of the static scene (the host's sparse cloud) or None; on a wide
    rig (reflow_plugin.rig.wide_rig) they guide DIS between different rig cameras (module docstring)."""

    name = "flow"

    def __init__(self, cameras: Sequence[Camera], stride: int = 1, anchors: np.ndarray | None = None,
                 spread: int = 1, finest_scale: int | None = None) -> None:
        super().__init__(cameras, stride)
        if int(spread) < 1:
            raise ValueError(f"flow provider: spread must be >= 1 (got {spread})")
        if finest_scale is not None and int(finest_scale) < 0:
            raise ValueError(f"flow provider: finest_scale must be >= 0 (got {finest_scale})")
        self.spread = int(spread)
        self._flows: dict[tuple[int, int], np.ndarray] = {}
        self._dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        # the preset stops at half resolution (level 1): at 160x90 a flow of 80x45
        self.finest_scale = None if finest_scale is None else int(finest_scale)
        if self.finest_scale is not None:
            self._dis.setFinestScale(self.finest_scale)
        order = sorted(range(len(self.cameras)), key=lambda k: (self.cameras[k].time, self.cameras[k].frame_index))
        self.rig = wide_rig([self.viewmats[k] for k in order])
        self.groups = pose_groups(self.viewmats)
        self.anchors = None if anchors is None or len(anchors) == 0 else np.asarray(anchors, np.float64)
        self._guides: dict[int, np.ndarray | None] = {}

    @property
    def fused(self) -> bool:
        """Whether `depth` fuses every partner within `spread` frames (a sequence, spread > 1)."""
        return not self.rig and self.spread > 1

    def key(self) -> str:
        dis = "" if self.finest_scale is None else f"|finest={self.finest_scale}"
        if not self.rig:
            return super().key() + (f"|spread={self.spread}" if self.fused else "") + dis
        return f"{super().key()}|rig" + ("|guided" if self.anchors is not None else "") + dis

    def partners(self, n: int) -> list[int]:
        """The frames n is triangulated with: its time neighbours n - k, n + k for k = 1 ..
        `spread` (frames are in time order), or on a wide rig the nearest frame in time of each of
        the two camera poses whose viewing direction is closest to n's (a different pose: a
        baseline to triangulate; a wide rig has at least two poses)."""
        if not self.rig:
            return [m for k in range(1, self.spread + 1) for m in (n - k, n + k) if 0 <= m < len(self.cameras)]
        best: dict[int, tuple[float, float, int]] = {}
        for m in range(len(self.cameras)):
            group = int(self.groups[m])
            if group == self.groups[n]:
                continue
            angle = viewing_angle_deg(self.viewmats[n], self.viewmats[m])
            rank = (angle, abs(self.cameras[m].time - self.cameras[n].time), m)
            if group not in best or rank < best[group]:
                best[group] = rank
        return [rank[2] for rank in sorted(best.values())[:2]]

    def guide(self, n: int) -> np.ndarray | None:
        """[H, W] z-depth of frame n interpolated from the anchors (None: no anchors, too few in view)."""
        if n not in self._guides:
            cam = self.cameras[n]
            self._guides[n] = (None if self.anchors is None else
                               guide_depth(self.anchors, self.K[n], self.viewmats[n], cam.height, cam.width))
        return self._guides[n]

    def guide_flow(self, i: int, j: int) -> np.ndarray | None:
        """[H, W, 2] float32 flow i -> j of the static scene at frame i's guide depth (None: no guide)."""
        depth = self.guide(i)
        if depth is None:
            return None
        H, W = depth.shape
        ys, xs = np.mgrid[0:H, 0:W] + 0.5
        pixels = np.stack([xs, ys, np.ones_like(xs)], -1)
        world = to_world((pixels @ np.linalg.inv(self.K[i]).T) * depth[..., None], self.viewmats[i])
        projected = to_camera(world, self.viewmats[j]) @ self.K[j].T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = projected[..., :2] / projected[..., 2:]
        flow = np.where((projected[..., 2:] > 1e-6) & np.isfinite(uv), uv - pixels[..., :2], 0.0)
        return flow.astype(np.float32)

    def flow(self, i: int, j: int) -> np.ndarray:
        """[H, W, 2] DIS flow from frame i to frame j (cached); on a rig with anchors, between two
        different rig cameras, refined from `guide_flow`."""
        if (i, j) not in self._flows:
            start = self.guide_flow(i, j) if self.rig and self.groups[i] != self.groups[j] else None
            self._flows[(i, j)] = self._dis.calc(_grey(self.cameras[i]), _grey(self.cameras[j]), start)
        return self._flows[(i, j)]

    def fb_error(self, i: int, j: int, full: bool = False) -> np.ndarray:
        """[h, w] squared forward-backward error (px^2) of flow i -> j on frame i's grid pixels
        (about 1e12 where the flow leaves frame j)."""
        rows, cols = self.grid(full)
        f = self.flow(i, j)[np.ix_(rows, cols)]
        u = cols[None, :] + 0.5 + f[..., 0]
        v = rows[:, None] + 0.5 + f[..., 1]
        back = cv2.remap(self.flow(j, i), (u - 0.5).astype(np.float32), (v - 0.5).astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(1e6, 1e6))
        return ((f + back) ** 2).sum(-1)

    def triangulate(self, i: int, j: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(world points [h, w, 3] of frame i's grid pixels, confidence [h, w]) from flow i -> j."""
        points, conf, _ = self._triangulate_with_fb(i, j, full)
        return points, conf

    def _triangulate_with_fb(self, i: int, j: int, full: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`triangulate`'s points and confidence, and the `fb_error` [h, w] they were weighted with."""
        rows, cols = self.grid(full)
        f = self.flow(i, j)[np.ix_(rows, cols)]
        u = cols[None, :] + 0.5 + f[..., 0]
        v = rows[:, None] + 0.5 + f[..., 1]
        fb = self.fb_error(i, j, full)
        Ki_inv, Kj_inv = np.linalg.inv(self.K[i]), np.linalg.inv(self.K[j])
        Ri, Rj = self.viewmats[i][:3, :3], self.viewmats[j][:3, :3]
        ci = -Ri.T @ self.viewmats[i][:3, 3]
        cj = -Rj.T @ self.viewmats[j][:3, 3]
        pi = np.stack(np.broadcast_arrays(cols[None, :] + 0.5, rows[:, None] + 0.5, 1.0), -1)
        pj = np.stack([u, v, np.ones_like(u)], -1)
        di = (pi @ Ki_inv.T) @ Ri  # world directions (R^T K^-1 p)
        dj = (pj @ Kj_inv.T) @ Rj
        # midpoint of the closest points of the two rays: solve [di, -dj] [a, b]^T = cj - ci
        b = cj - ci
        aa, bb, ab = (di * di).sum(-1), (dj * dj).sum(-1), (di * dj).sum(-1)
        db, ebb = (di * b).sum(-1), (dj * b).sum(-1)
        det = aa * bb - ab ** 2
        safe = np.where(np.abs(det) > 1e-12, det, 1e-12)
        lam_i = (bb * db - ab * ebb) / safe
        lam_j = (ab * db - aa * ebb) / safe
        points = 0.5 * (ci + lam_i[..., None] * di + cj + lam_j[..., None] * dj)
        cos = ab / np.sqrt(aa * bb)
        angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        inside = (u >= 0) & (u < self.cameras[j].width) & (v >= 0) & (v < self.cameras[j].height)
        conf = np.exp(-fb / 2.0) * np.minimum(1.0, angle / MIN_ANGLE_DEG)
        ok = inside & (lam_i > 0) & (lam_j > 0) & (np.abs(det) > 1e-12) & np.isfinite(points).all(-1)
        return points, np.where(ok, conf, 0.0), fb

    def depth(self, n: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Triangulated with the `partners`: per pixel the more confident of the two, or with
        `spread` > 1 on a sequence their fusion (`fused_depth`)."""
        if len(self.cameras) < 2:
            raise ValueError("flow provider: a single frame has no flow to triangulate")
        if self.fused:
            return self.fused_depth(n, full)
        best_z, best_c = None, None
        for m in self.partners(n):
            points, conf = self.triangulate(n, m, full)
            z = to_camera(points, self.viewmats[n])[..., 2]
            if best_z is None:
                best_z, best_c = z, conf
            else:
                better = conf > best_c
                best_z, best_c = np.where(better, z, best_z), np.where(better, conf, best_c)
        good = best_c > 0
        fill = float(np.median(best_z[good])) if good.any() else 1.0
        return np.where(good, best_z, fill), best_c

    def fused_depth(self, n: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(z-depth [h, w], confidence [h, w]) of frame n from every partner within `spread` frames.

        A camera that pans more than it moves gives neighbouring frames a triangulation angle of a
        fraction of a degree (DAVIS at 160x90: 0.26 degrees between frames n and n + 1 of dog),
        where a tenth of a pixel of flow error is several percent of depth. Farther partners see a
        wider angle but flow that is harder to match. Per pixel each partner m gives an inverse depth
        u_m; its error is about (flow error) / (parallax), the parallax in pixels being
        p_m = focal x |c_m - c_n| x u_ref (camera centres; u_ref the plain median of the u_m, so a
        flow that went wrong does not inflate its own weight). Beyond a few pixels the flow's own
        error grows with the displacement, so the weight is exp(-|forward-backward error|^2 / 2) x
        min(p_m, FUSED_SATURATION_PX)^2: a slow pan leans on its far partners, a fast one weighs
        them all alike. The depth is the weighted median of the u_m (robust to a failed partner).
        Confidence: exp(-(s / FUSED_AGREEMENT)^2), s = the weighted mean |u_m - u| / u, the
        partners' relative disagreement, times min(1, p / FUSED_MIN_PARALLAX_PX), p = focal x
        baseline x u the parallax in pixels of the widest partner at the fused depth (partners
        that agree because none of them moved measure nothing).
        """
        ci = -self.viewmats[n][:3, :3].T @ self.viewmats[n][:3, 3]
        inverse, flow_terms, baselines = [], [], []
        for m in self.partners(n):
            points, conf, fb = self._triangulate_with_fb(n, m, full)
            z = to_camera(points, self.viewmats[n])[..., 2]
            baseline = float(np.linalg.norm(ci + self.viewmats[m][:3, :3].T @ self.viewmats[m][:3, 3]))
            usable = (conf > 0) & (z > 0) & np.isfinite(z)
            inverse.append(np.where(usable, 1.0 / np.where(usable, z, 1.0), np.nan))
            # triangulate's confidence without its angle factor
            flow_terms.append(np.where(usable, np.exp(-fb / 2.0), 0.0))
            baselines.append(np.where(usable, baseline, 0.0))
        u, b = np.stack(inverse), np.stack(baselines)  # [K, h, w]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: no partner usable
            reference = np.nan_to_num(np.nanmedian(u, axis=0), nan=0.0)
        u = np.nan_to_num(u, nan=0.0)
        w = np.stack(flow_terms) * np.minimum(self.K[n][0, 0] * b * reference[None], FUSED_SATURATION_PX) ** 2
        order = np.argsort(u, axis=0)
        u_sorted, w_sorted = np.take_along_axis(u, order, 0), np.take_along_axis(w, order, 0)
        cumulative = np.cumsum(w_sorted, 0)
        total = cumulative[-1]
        middle = (cumulative < 0.5 * total[None]).sum(0).clip(max=len(u) - 1)
        fused = np.take_along_axis(u_sorted, middle[None], 0)[0]
        good = (total > 0) & (fused > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            spread = (w * np.abs(u - fused[None])).sum(0) / np.where(good, total * fused, 1.0)
        parallax = self.K[n][0, 0] * b.max(0) * np.where(good, fused, 0.0)
        conf = np.where(good, np.exp(-(spread / FUSED_AGREEMENT) ** 2)
                        * np.minimum(1.0, parallax / FUSED_MIN_PARALLAX_PX), 0.0)
        z = np.where(good, 1.0 / np.where(good, fused, 1.0), 0.0)
        fill = float(np.median(z[good])) if good.any() else 1.0
        return np.where(good, z, fill), conf

    def pair(self, i: int, j: int) -> PairPrediction:
        Pi, Ci = self.triangulate(i, j)
        Pj, Cj = self.triangulate(j, i)
        V = self.viewmats[i]
        return PairPrediction(to_camera(Pi, V), to_camera(Pj, V), Ci, Cj).sanitized()


__all__ = ["PairPrediction", "PointmapProvider", "DepthProvider", "FlowProvider", "guide_depth"]
