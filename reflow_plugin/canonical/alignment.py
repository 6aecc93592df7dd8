"""Global alignment of pairwise pointmaps (DUSt3R-style, written here).

    states, report = align_frames(provider, frames, edges, weights, fixed={}, free_poses=False)

Unknowns: per frame n a scale a_n and shift b_n of the provider's depth D_n (world pointmap
chi_n = R_n^T (ray * (a_n D_n + b_n) - t_n)), per edge e = (i, j) a similarity
S_e = (sigma_e, R_e, t_e) that maps the pair's pointmaps X_i^e, X_j^e (camera i's frame) to the
world, and, with `free_poses`, the camera poses. Loss (confidence-weighted 3D distance):

    sum_e sum_{v in e} sum_p C_v^e(p) |chi_v(p) - S_e X_v^e(p)| / z_v(p) / sum C

each distance relative to the point's aligned depth z_v (an absolute distance rewards shrinking
the scene, since the pointmaps' noise shrinks with it).

Cameras are held fixed when the dataset gives them (the normal case): the camera baselines then
fix the metric scale. With `free_poses`, every pose but the root's (the gauge: pose and depth
scale) is optimised too.

Initialisation: maximum spanning tree of the pair graph (edge weight = summed confidence). The
root (a frame in `fixed`, else the best-connected frame) gets its depth scale from the pair
geometry (fixed cameras: the scale at which the pair's relative translation matches the dataset's;
free poses: 1). Walking the tree, each edge's similarity is a weighted Umeyama fit onto the known
frame's pointmap and the new frame's scale (and pose) follow from the edge's prediction of it.
Then every edge's similarity is fitted and Adam (cosine-decaying learning rate) refines all.

Degenerate input: an edge whose confidence sums to 0 is dropped (reported); a frame left with
no edge keeps its camera, shift 0 and the median scale of the aligned frames (fixed cameras;
reported in `unaligned`); with free poses a disconnected graph is a ValueError naming the frames.
"""
from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from tqdm import tqdm

from .geometry import rays as grid_rays
from .geometry import relative, robust_umeyama, rotvec_to_matrix, to_camera, to_world
from .providers import PairPrediction, PointmapProvider

log = logging.getLogger(__name__)
BLOCK_ROUNDS = 5


@dataclass
class FrameState:
    """Aligned frame: depth = scale * D + shift, or with `inverse` 1 / depth = scale * d + shift on
    the provider's inverse depth d (canonical/inverse.py); viewmat [4, 4] world -> camera."""

    scale: float
    shift: float
    viewmat: np.ndarray
    determined: bool = True  # False: the scale is a fallback (no camera baseline, no edge)
    inverse: bool = False
    max_depth: float = float("inf")  # inverse states: farther pixels carry no depth

    def metric_depth(self, provider: PointmapProvider, n: int, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(metric z-depth [h, w], provider confidence [h, w]) of frame n; NaN where not positive
        (or, inverse, beyond max_depth)."""
        if not self.inverse:
            depth, conf = provider.depth(n, full)
            return self.scale * np.asarray(depth, np.float64) + self.shift, conf
        d, conf = provider.inverse_depth(n, full)
        u = self.scale * np.asarray(d, np.float64) + self.shift
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(u > 0, 1.0 / u, np.nan)
        return np.where(z <= self.max_depth, z, np.nan), conf


@dataclass
class _Frame:
    depth: np.ndarray  # [P] provider depth on the grid
    rays: np.ndarray  # [P, 3] z = 1 directions
    weight: np.ndarray  # [P] provider confidence x mask weight


def _median_ratio(num: np.ndarray, den: np.ndarray, weight: np.ndarray) -> float | None:
    ok = (weight > 0) & np.isfinite(num) & np.isfinite(den) & (den > 0) & (num > 0)
    return float(np.median(num[ok] / den[ok])) if ok.sum() >= 3 else None


def _world(state: FrameState, f: _Frame) -> np.ndarray:
    return to_world(f.rays * (state.scale * f.depth + state.shift)[:, None], state.viewmat)


def _view(pair: PairPrediction, first: bool) -> tuple[np.ndarray, np.ndarray]:
    """([P, 3], [P]) pointmap and confidence of the pair's first (i) or second (j) frame."""
    X, C = (pair.X_ii, pair.C_ii) if first else (pair.X_ji, pair.C_ji)
    return X.reshape(-1, 3), C.reshape(-1)


def root_scale(pair: PairPrediction, i: int, j: int, root: int, frames: Mapping[int, _Frame],
               viewmats: Mapping[int, np.ndarray]) -> float | None:
    """Depth scale of `root` (i or j) at which the pair matches the dataset's relative pose.

    X_ji = s (R y_j + t) with y_j along frame j's rays: s = sum (P w).(P c) / sum |P c|^2 with
    w = R^T X_ji, c = R^T t and P the projection orthogonal to each ray. None without a baseline.
    """
    T = relative(viewmats[i], viewmats[j])
    R, t = T[:3, :3], T[:3, 3]
    X, C = _view(pair, False)
    w, c = X @ R, R.T @ t
    ray = frames[j].rays / np.linalg.norm(frames[j].rays, axis=1, keepdims=True)
    Pw = w - ray * (ray * w).sum(1, keepdims=True)
    Pc = c - ray * (ray @ c)[:, None]
    C = C * frames[j].weight
    den = float((C * (Pc ** 2).sum(1)).sum())
    if den <= 1e-12 * max(float(C.sum()), 1e-12) * max(float(c @ c), 1e-12) or den <= 0:
        return None
    s = float((C * (Pw * Pc).sum(1)).sum()) / den
    if not s > 0:
        return None
    if root == i:
        Xi, Ci = _view(pair, True)
        return _median_ratio(Xi[:, 2] / s, frames[i].depth, Ci * frames[i].weight)
    y = w / s - c
    return _median_ratio(y[:, 2], frames[j].depth, C)


def _edge_fit(pair: PairPrediction, states: Mapping[int, FrameState], frames: Mapping[int, _Frame],
              i: int, j: int, use: Sequence[int]) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity of edge (i, j) fitted on the frames in `use` (whose states are known)."""
    src, dst, wts = [], [], []
    for v in use:
        X, C = _view(pair, v == i)
        src.append(X)
        dst.append(_world(states[v], frames[v]))
        wts.append(C * frames[v].weight)
    return robust_umeyama(np.concatenate(src), np.concatenate(dst), np.concatenate(wts))


def _root(members: Sequence[int], root: int, pairs: Mapping[tuple[int, int], PairPrediction],
          frames: Mapping[int, _Frame], viewmats: Mapping[int, np.ndarray], free_poses: bool,
          strength: np.ndarray, index: Mapping[int, int]) -> tuple[int, float | None]:
    """(root frame, its depth scale): free poses fix the gauge at scale 1; fixed cameras take the
    best-connected frame whose pairs have a camera baseline (None when no frame has one)."""
    if free_poses:
        return root, 1.0
    for n in sorted(members, key=lambda m: (m != root, -strength[index[m]])):
        found = [root_scale(p, i, j, n, frames, viewmats) for (i, j), p in pairs.items() if n in (i, j)]
        found = [s for s in found if s is not None]
        if found:
            return n, float(np.median(found))
    log.warning("canonical: no camera baseline between frames %s: their depth scale is taken as 1",
                sorted(members)[:8])
    return root, None


def _initial_states(frames: dict[int, _Frame], pairs: dict[tuple[int, int], PairPrediction],
                    weights: dict[tuple[int, int], float], viewmats: Mapping[int, np.ndarray],
                    fixed: Mapping[int, FrameState], free_poses: bool) -> tuple[dict[int, FrameState], list[int]]:
    """Spanning-tree initialisation; returns (states, frames left without any edge)."""
    order = sorted(frames)
    index = {n: k for k, n in enumerate(order)}
    top = max(weights.values(), default=1.0)
    rows = [index[i] for i, _ in weights]
    cols = [index[j] for _, j in weights]
    cost = [top * 1.01 - w + 1e-9 for w in weights.values()]  # max spanning tree = min tree of (top - w)
    graph = coo_matrix((cost, (rows, cols)), shape=(len(order),) * 2).tocsr()
    tree = minimum_spanning_tree(graph)
    tree = tree + tree.T
    count, component = connected_components(graph, directed=False)
    strength = np.zeros(len(order))
    for (i, j), w in weights.items():
        strength[index[i]] += w
        strength[index[j]] += w
    states: dict[int, FrameState] = dict(fixed)
    lonely: list[int] = []
    for comp in range(count):
        members = [order[k] for k in np.flatnonzero(component == comp)]
        anchored = [n for n in members if n in fixed]
        best = max(members, key=lambda n: strength[index[n]])
        root = anchored[0] if anchored else (members[0] if free_poses else best)
        if len(members) == 1 and root not in fixed:
            lonely.append(root)
            continue
        if root not in states:
            root, scale = _root(members, root, pairs, frames, viewmats, free_poses, strength, index)
            states[root] = FrameState(1.0 if scale is None else scale, 0.0, viewmats[root], scale is not None)
        visit, parent = breadth_first_order(tree, index[root], directed=False)
        for k in visit[1:]:
            v, u = order[k], order[parent[k]]
            if v in states:
                continue
            i, j = (u, v) if (u, v) in pairs else (v, u)
            s, R, t = _edge_fit(pairs[(i, j)], states, frames, i, j, [u])
            X, C = _view(pairs[(i, j)], v == i)
            predicted = s * X @ R.T + t
            weight = C * frames[v].weight
            if free_poses:
                a, Rv, tv = robust_umeyama(frames[v].rays * frames[v].depth[:, None], predicted, weight)
                viewmat = np.eye(4)
                viewmat[:3, :3], viewmat[:3, 3] = Rv.T, -Rv.T @ tv
                states[v] = FrameState(a, 0.0, viewmat, states[u].determined)
            else:
                z = to_camera(predicted, viewmats[v])[:, 2]
                a = _median_ratio(z, frames[v].depth, weight)
                states[v] = FrameState(a if a is not None else states[u].scale, 0.0, viewmats[v],
                                       states[u].determined and a is not None)
    _block_rounds(frames, pairs, states, fixed, free_poses)
    if lonely:
        aligned = [s.scale for n, s in states.items() if n in frames]
        fallback = float(np.median(aligned)) if aligned else 1.0
        for n in lonely:
            states[n] = FrameState(fallback, 0.0, viewmats[n], False)
    return states, lonely


def _block_rounds(frames: Mapping[int, _Frame], pairs: Mapping[tuple[int, int], PairPrediction],
                  states: dict[int, FrameState], fixed: Mapping[int, FrameState], free_poses: bool,
                  rounds: int = BLOCK_ROUNDS) -> None:
    """Closed-form block coordinate descent after the tree (in place): fit every edge's similarity
    to the current frames, then every free frame's scale (and pose) to all its edges' predictions.
    Spreads the tree's accumulated error over the whole graph before Adam polishes."""
    gauge = set(fixed) or {min(frames)}
    for _ in range(rounds):
        edges = {e: _edge_fit(p, states, frames, *e, [v for v in e if v in states]) for e, p in pairs.items()}
        predicted: dict[int, list] = {}
        for (i, j), (s, R, t) in edges.items():
            for v in (i, j):
                X, C = _view(pairs[(i, j)], v == i)
                predicted.setdefault(v, []).append((s * X @ R.T + t, C * frames[v].weight))
        for v, items in predicted.items():
            if v in fixed or v not in states:
                continue
            target, weight = np.concatenate([x for x, _ in items]), np.concatenate([w for _, w in items])
            local = np.tile(frames[v].rays * frames[v].depth[:, None], (len(items), 1))
            if free_poses:
                if v in gauge:
                    continue
                a, Rv, tv = robust_umeyama(local, target, weight)
                viewmat = np.eye(4)
                viewmat[:3, :3], viewmat[:3, 3] = Rv.T, -Rv.T @ tv
                states[v] = FrameState(a, 0.0, viewmat, states[v].determined)
            else:
                z = to_camera(target, states[v].viewmat)[:, 2]
                a = _median_ratio(z, local[:, 2], weight)
                if a is not None:
                    states[v] = FrameState(a, 0.0, states[v].viewmat, states[v].determined)


def _gather(provider: PointmapProvider, frames: Sequence[int], edges: Sequence[tuple[int, int]],
            weights: Mapping[int, np.ndarray]) -> tuple[dict[int, _Frame], dict, dict, list]:
    rows, cols = provider.grid()
    data: dict[int, _Frame] = {}
    for n in frames:
        depth, conf = provider.depth(n)
        depth = np.asarray(depth, np.float64).reshape(-1)
        good = np.isfinite(depth) & (depth > 0)
        if not good.any():
            raise ValueError(f"canonical: provider '{provider.name}' returned no finite positive depth for frame "
                             f"{n} ({provider.cameras[n].image_name})")
        w = np.where(good, np.nan_to_num(np.asarray(conf, np.float64).reshape(-1)).clip(min=0), 0.0)
        data[n] = _Frame(np.where(good, depth, 1.0), grid_rays(provider.K[n], rows, cols).reshape(-1, 3),
                         w * weights[n].reshape(-1))
    pairs, edge_weight, dropped = {}, {}, []
    for i, j in edges:
        pair = provider.pair(i, j).sanitized()
        sides = [float((pair.C_ii.reshape(-1) * data[i].weight).sum()),
                 float((pair.C_ji.reshape(-1) * data[j].weight).sum())]
        total = sum(sides)
        if not min(sides) > 0:  # an edge needs evidence on both of its frames
            dropped.append([i, j])
            continue
        pairs[(i, j)], edge_weight[(i, j)] = pair, total
    return data, pairs, edge_weight, dropped


def _check_connected(frames: Sequence[int], edges: Sequence[tuple[int, int]], fixed: Mapping[int, FrameState],
                     names: Sequence[str]) -> None:
    """Free poses: every frame must be connected to the root's component."""
    order = sorted(frames)
    index = {n: k for k, n in enumerate(order)}
    graph = coo_matrix((np.ones(len(edges)), ([index[i] for i, _ in edges], [index[j] for _, j in edges])),
                       shape=(len(order),) * 2)
    count, component = connected_components(graph, directed=False)
    if count > 1:
        root = next((n for n in order if n in fixed), order[0])
        cut = [names[n] for n in order if component[index[n]] != component[index[root]]]
        raise ValueError(f"canonical: the pair graph is disconnected (free poses need one component): "
                         f"{len(cut)} frame(s) not connected to {names[root]}: {', '.join(cut[:8])}")


def align_frames(provider: PointmapProvider, frames: Sequence[int], edges: Sequence[tuple[int, int]],
                 weights: Mapping[int, np.ndarray], fixed: Mapping[int, FrameState] | None = None,
                 free_poses: bool = False, iterations: int = 300, lr: float = 0.003,
                 progress: bool = False, desc: str = "align", device: torch.device | str = "cpu"
                 ) -> tuple[dict[int, FrameState], dict]:
    """Align `frames` (camera indices) over the pair graph `edges` (i, j).

    weights: per frame [h, w] multipliers of the confidence (0 on dynamic pixels).
    fixed: frames whose state is known (kept as is; the anchors of a clip).
    The per-frame depth shift stays at its initial value: a free shift trades against the scale
    with noisy pointmaps and compressed the depth range, measured 15% too shallow with 2% depth
    noise on the simulator (the `--canonical_shift` flag, removed 2026-11-26).
    Returns ({frame: FrameState}, report with residuals, edge counts and seconds).
    """
    start = time.perf_counter()
    fixed = dict(fixed or {})
    frames = sorted(set(frames) | set(fixed))
    data, pairs, edge_weight, dropped = _gather(provider, frames, edges, weights)
    names = [c.image_name for c in provider.cameras]
    if free_poses:
        _check_connected(frames, list(pairs), fixed, names)
    viewmats = {n: provider.viewmats[n] for n in frames}
    states, lonely = _initial_states(data, pairs, edge_weight, viewmats, fixed, free_poses)
    report = {"frames": len(frames), "edges": len(pairs), "dropped_edges": dropped,
              "unaligned": [names[n] for n in lonely]}
    if not pairs:
        report.update(residual_init=None, residual=None, seconds=time.perf_counter() - start)
        return {n: states[n] for n in frames}, report
    states, residuals = _refine(data, pairs, states, fixed, free_poses, iterations, lr, progress, desc, device)
    report.update(residual_init=residuals[0], residual=residuals[1], seconds=time.perf_counter() - start)
    return {n: states[n] for n in frames}, report


def _refine(data: dict[int, _Frame], pairs: dict[tuple[int, int], PairPrediction], states: dict[int, FrameState],
            fixed: Mapping[int, FrameState], free_poses: bool, iterations: int, lr: float, progress: bool,
            desc: str, device) -> tuple[dict[int, FrameState], tuple[float, float]]:
    """Adam over scales, edge similarities (and free poses); residuals before/after
    (weighted mean 3D distance relative to depth)."""
    order = sorted(data)
    index = {n: k for k, n in enumerate(order)}
    T = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
    ref = float(np.median(np.concatenate([states[n].scale * data[n].depth[data[n].weight > 0] for n in order]
                                         + [np.ones(1)])))
    ref = ref if ref > 0 else 1.0
    D, rays = T([data[n].depth for n in order]), T([data[n].rays for n in order])
    a0 = T([np.log(max(states[n].scale, 1e-9)) for n in order])
    b0 = T([states[n].shift / ref for n in order])
    R0 = T([states[n].viewmat[:3, :3] for n in order])
    t0 = T([states[n].viewmat[:3, 3] / ref for n in order])
    roots = set(fixed) if fixed else {order[0]}
    free_frame = T([0.0 if n in fixed else 1.0 for n in order])
    free_pose = T([1.0 if free_poses and n not in roots else 0.0 for n in order])
    free_scale = free_frame * (1 - T([1.0 if free_poses and n in roots else 0.0 for n in order]))
    ei = torch.as_tensor([index[i] for i, _ in pairs], device=device)
    ej = torch.as_tensor([index[j] for _, j in pairs], device=device)
    Xi = T([p.X_ii.reshape(-1, 3) for p in pairs.values()])
    Xj = T([p.X_ji.reshape(-1, 3) for p in pairs.values()])
    Wi = T([p.C_ii.reshape(-1) * data[i].weight for (i, j), p in pairs.items()])
    Wj = T([p.C_ji.reshape(-1) * data[j].weight for (i, j), p in pairs.items()])
    fits = [_edge_fit(p, states, data, i, j, [i, j]) for (i, j), p in pairs.items()]
    ls0 = T([np.log(max(s, 1e-12)) - np.log(ref) for s, _, _ in fits])
    Rs0 = T([R for _, R, _ in fits])
    ts0 = T([t / ref for _, _, t in fits])
    E, F = len(pairs), len(order)
    params = {k: torch.zeros(shape, device=device, requires_grad=True) for k, shape in
              (("a", (F,)), ("w", (F, 3)), ("t", (F, 3)), ("s", (E,)), ("we", (E, 3)), ("te", (E, 3)))}
    total = Wi.sum() + Wj.sum()

    def loss_fn() -> torch.Tensor:
        scale = torch.exp(a0 + free_scale * params["a"])
        depth = (scale[:, None] * D + b0[:, None]) / ref
        R = rotvec_to_matrix(free_pose[:, None] * params["w"]) @ R0
        t = t0 + free_pose[:, None] * params["t"]
        chi = torch.einsum("fji,fpj->fpi", R, rays * depth[..., None] - t[:, None])  # R^T (p - t)
        Rs = rotvec_to_matrix(params["we"]) @ Rs0
        sig = torch.exp(ls0 + params["s"])[:, None, None]
        ts = (ts0 + params["te"])[:, None]
        # relative to the point's own depth: an absolute distance would reward shrinking the scene
        # (noise shrinks with it; measured 5% too small after 100 steps with 2% depth noise)
        z = depth.clamp(min=1e-6)
        di = (chi[ei] - (sig * Xi @ Rs.transpose(1, 2) + ts)).norm(dim=-1) / z[ei]
        dj = (chi[ej] - (sig * Xj @ Rs.transpose(1, 2) + ts)).norm(dim=-1) / z[ej]
        return ((Wi * di).sum() + (Wj * dj).sum()) / total

    optimizer = torch.optim.Adam(params.values(), lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, max(iterations, 1), eta_min=lr * 0.01)
    with torch.no_grad():
        initial = float(loss_fn())
    # the training bar's rule: a bar on a terminal only; in a log file (CI, clusters) its carriage
    # returns (set_postfix redraws every step, whatever mininterval says) would flood the log
    bar = tqdm(range(iterations), desc=desc, disable=not progress or not sys.stderr.isatty(), leave=False)
    for _ in bar:
        optimizer.zero_grad()
        loss = loss_fn()
        loss.backward()
        optimizer.step()
        schedule.step()
        bar.set_postfix(residual=f"{float(loss.detach()):.4f}")
    with torch.no_grad():
        final = float(loss_fn())
        scale = torch.exp(a0 + free_scale * params["a"]).cpu().double().numpy()
        shift = (b0 * ref).cpu().double().numpy()
        R = (rotvec_to_matrix(free_pose[:, None] * params["w"]) @ R0).cpu().double().numpy()
        t = ((t0 + free_pose[:, None] * params["t"]) * ref).cpu().double().numpy()
    out = {}
    for k, n in enumerate(order):
        if n in fixed:
            out[n] = fixed[n]
            continue
        viewmat = np.eye(4)
        viewmat[:3, :3], viewmat[:3, 3] = R[k], t[k]
        out[n] = FrameState(float(scale[k]), float(shift[k]), viewmat if free_poses else states[n].viewmat,
                            states[n].determined)
    return out, (initial, final)
