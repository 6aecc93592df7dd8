"""Ray intersection and surface normals of the unit shapes, in the shape's own (unit) frame.

Every renderable object is one unit shape mapped to the world by an affine matrix (pose, non-rigid
deformation and size). A ray is intersected in the unit frame: origin ``o`` (one point, the camera
centre carried into the frame) and directions ``d`` [M,3] carried by the inverse linear part, NOT
renormalised. Because the map is affine, the ray parameter ``s`` of a hit is the same in the unit
frame and in the world, so the caller's world-space parametrisation (where ``s`` is the camera
z-depth) survives the change of frame exactly. This is what makes time-varying affine
deformations (scaling, shearing) exactly ray-castable.

Unit shapes:
    sphere    |p| = 1 (an ellipsoid once sized)
    box       [-1, 1]^3 seen from outside
    room      [-1, 1]^3 seen from inside (the exit point): an enclosing backdrop with floor and walls
    cylinder  x^2 + z^2 = 1, |y| <= 1, with caps (axis along local y)
    quad      z = 0, |x| <= 1, |y| <= 1 (two-sided; thin ribbons, panels)
    group     no geometry: a pivot that carries children in a hierarchy
"""
from __future__ import annotations

import numpy as np

RENDERABLE_SHAPES = ("sphere", "box", "room", "cylinder", "quad")
SHAPES = RENDERABLE_SHAPES + ("group",)

# Smallest accepted ray parameter: hits closer than this to the camera centre are ignored.
RAY_EPS = 1e-6


def intersect(shape: str, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit of rays ``origin + s * dirs`` with a unit shape.

    Args:
        shape: one of ``RENDERABLE_SHAPES``.
        origin: [3] ray origin in the unit frame.
        dirs: [M,3] ray directions in the unit frame (any length).
    Returns:
        [M] float64, ``inf`` where the ray misses.
    """
    if shape == "sphere":
        return _sphere(origin, dirs)
    if shape == "box":
        return _box(origin, dirs, inside=False)
    if shape == "room":
        return _box(origin, dirs, inside=True)
    if shape == "cylinder":
        return _cylinder(origin, dirs)
    if shape == "quad":
        return _quad(origin, dirs)
    raise ValueError(f"shape {shape!r} has no geometry; expected one of {RENDERABLE_SHAPES}")


def local_normal(shape: str, points: np.ndarray) -> np.ndarray:
    """Outward (for ``room``: inward) unit-frame normal at surface points [M,3] -> [M,3]."""
    if shape == "sphere":
        return points.copy()
    if shape in ("box", "room"):
        axis = np.argmax(np.abs(points), axis=1)
        normal = np.zeros_like(points)
        rows = np.arange(points.shape[0])
        normal[rows, axis] = np.sign(points[rows, axis])
        return -normal if shape == "room" else normal
    if shape == "cylinder":
        radial = np.hypot(points[:, 0], points[:, 2])
        on_cap = (1.0 - np.abs(points[:, 1])) < np.abs(1.0 - radial)
        normal = np.stack([points[:, 0], np.zeros(len(points)), points[:, 2]], axis=1)
        normal[on_cap] = 0.0
        normal[on_cap, 1] = np.sign(points[on_cap, 1])
        return normal
    if shape == "quad":
        normal = np.zeros_like(points)
        normal[:, 2] = 1.0
        return normal
    raise ValueError(f"shape {shape!r} has no geometry; expected one of {RENDERABLE_SHAPES}")


def _nearest_positive(*candidates: np.ndarray) -> np.ndarray:
    """Element-wise smallest candidate larger than RAY_EPS (NaN and non-positive count as misses)."""
    best = np.full(candidates[0].shape, np.inf)
    for cand in candidates:
        ok = cand > RAY_EPS  # False for NaN
        best = np.where(ok & (cand < best), cand, best)
    return best


def _sphere(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    a = np.einsum("ij,ij->i", d, d)
    b = d @ o
    c = float(o @ o) - 1.0
    disc = b * b - a * c
    hit = disc >= 0.0
    root = np.sqrt(np.where(hit, disc, 0.0))
    near = np.where(hit, (-b - root) / a, np.nan)
    far = np.where(hit, (-b + root) / a, np.nan)
    return _nearest_positive(near, far)


def _box(o: np.ndarray, d: np.ndarray, inside: bool) -> np.ndarray:
    t_enter = np.full(len(d), -np.inf)
    t_exit = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            inv = 1.0 / d[:, axis]
            t0 = (-1.0 - o[axis]) * inv
            t1 = (1.0 - o[axis]) * inv
            # fmin/fmax skip the NaN of 0 * inf (a ray parallel to a slab, exactly on its face).
            np.fmax(t_enter, np.fmin(t0, t1), out=t_enter)
            np.fmin(t_exit, np.fmax(t0, t1), out=t_exit)
    crosses = t_enter <= t_exit
    if inside:
        return _nearest_positive(np.where(crosses, t_exit, np.nan))
    return _nearest_positive(np.where(crosses, t_enter, np.nan), np.where(crosses, t_exit, np.nan))


def _cylinder(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    a = dx * dx + dz * dz
    b = o[0] * dx + o[2] * dz
    c = o[0] ** 2 + o[2] ** 2 - 1.0
    disc = b * b - a * c
    hit = (disc >= 0.0) & (a > 0.0)
    root = np.sqrt(np.where(hit, disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        side = []
        for sign in (-1.0, 1.0):
            s = np.where(hit, (-b + sign * root) / a, np.nan)
            y = o[1] + s * dy
            side.append(np.where(np.abs(y) <= 1.0, s, np.nan))
        caps = []
        for level in (-1.0, 1.0):
            s = (level - o[1]) / dy
            x = o[0] + s * dx
            z = o[2] + s * dz
            caps.append(np.where(x * x + z * z <= 1.0, s, np.nan))
    return _nearest_positive(*side, *caps)


def _quad(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[2] / d[:, 2]
    x = o[0] + s * d[:, 0]
    y = o[1] + s * d[:, 1]
    return _nearest_positive(np.where((np.abs(x) <= 1.0) & (np.abs(y) <= 1.0), s, np.nan))
