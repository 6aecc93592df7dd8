"""Procedural surface textures, evaluated in an object's local rest-shape coordinates.

Textures are functions of the surface point expressed in the object's own frame (unit-shape
coordinates times the object's size, i.e. metric units before any non-rigid deformation), so the
pattern travels and deforms with its object and photometric warping between frames carries signal.
``flat`` is the deliberately textureless case.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.ndimage import map_coordinates

from ._validate import check_choice, check_color, check_positive, check_range

TEXTURE_KINDS = ("flat", "checker", "stripes", "noise")


@dataclass(frozen=True)
class Texture:
    """A procedural texture.

    Attributes:
        kind: ``flat`` (one colour, textureless), ``checker`` (3D checkerboard), ``stripes``
            (bands across ``axis``) or ``noise`` (smooth multi-octave value noise).
        colors: two RGB colours in [0, 1]; ``flat`` uses the first.
        period: size of one checker cell / stripe pair / noise feature, in scene units.
        detail: strength in [0, 1] of a finer noise that modulates the base pattern, so large
            uniform cells still carry texture. 0 for none.
        axis: local axis (0, 1, 2) across which ``stripes`` alternate.
    """

    kind: str = "noise"
    colors: tuple = ((0.85, 0.85, 0.85), (0.15, 0.15, 0.15))
    period: float = 0.25
    detail: float = 0.0
    axis: int = 0

    def __post_init__(self) -> None:
        check_choice("Texture.kind", self.kind, TEXTURE_KINDS)
        if not isinstance(self.colors, (tuple, list)) or len(self.colors) != 2:
            raise ValueError(f"Texture.colors must be two RGB colours, got {self.colors!r}")
        object.__setattr__(self, "colors", tuple(check_color(f"Texture.colors[{i}]", c)
                                                 for i, c in enumerate(self.colors)))
        object.__setattr__(self, "period", check_positive("Texture.period", self.period))
        object.__setattr__(self, "detail", check_range("Texture.detail", self.detail, 0.0, 1.0))
        if self.axis not in (0, 1, 2) or isinstance(self.axis, bool):
            raise ValueError(f"Texture.axis must be 0, 1 or 2, got {self.axis!r}")


def albedo(texture: Texture, points: np.ndarray, seed: int) -> np.ndarray:
    """Surface colour of ``texture`` at local rest-shape points [M,3] -> [M,3] float64 in [0, 1].

    ``seed`` decorrelates the noise of different objects and different scene seeds.
    """
    c0 = np.asarray(texture.colors[0])
    c1 = np.asarray(texture.colors[1])
    scaled = points / texture.period
    if texture.kind == "flat":
        weight = np.zeros(len(points))
    elif texture.kind == "checker":
        # The quarter-cell offset keeps cell borders off the symmetry planes of the unit shapes
        # (a quad lies in z = 0), where a checker would degenerate into a single colour.
        cells = np.floor(scaled + 0.25).astype(np.int64)
        weight = (cells.sum(axis=1) & 1).astype(np.float64)
    elif texture.kind == "stripes":
        weight = (np.floor(scaled[:, texture.axis] + 0.25).astype(np.int64) & 1).astype(np.float64)
    else:  # noise
        weight = fractal_noise(scaled, seed, octaves=3)
        weight = np.clip((weight - 0.5) * 1.6 + 0.5, 0.0, 1.0)  # stretch contrast
    color = c0 + weight[:, None] * (c1 - c0)
    if texture.detail > 0.0:
        fine = fractal_noise(scaled * 3.0, seed, octaves=1, salt=1)
        color = color * ((1.0 - texture.detail) + texture.detail * 2.0 * fine)[:, None]
    return np.clip(color, 0.0, 1.0)


def fractal_noise(points: np.ndarray, seed: int, octaves: int, salt: int = 0) -> np.ndarray:
    """Sum of ``octaves`` octaves of smooth value noise at points [M,3] -> [M] in [0, 1].

    ``salt`` picks an independent-looking noise from the same seed (a different lattice shift).
    """
    coords = np.ascontiguousarray(points.T)  # [3, M], the layout map_coordinates wants
    total = np.zeros(len(points))
    norm = 0.0
    for octave in range(octaves):
        amplitude = 0.5 ** octave
        total += amplitude * value_noise(coords * (2.0 ** octave), seed, salt * 16 + octave)
        norm += amplitude
    return total / norm


def value_noise(coords: np.ndarray, seed: int, salt: int = 0) -> np.ndarray:
    """Smooth lattice value noise at points given as [3, M] -> [M] in [0, 1) (overwrites coords).

    Random values on the integer lattice (a periodic table of ``_LATTICE`` cells per axis drawn
    from ``seed``, entered at a ``salt``-dependent shift), interpolated with smoothstep weights:
    the fractional coordinates are remapped by smoothstep and handed to a compiled trilinear
    interpolation.
    """
    coords += _lattice_shift(seed, salt)[:, None]
    frac = np.mod(coords, 1.0)
    # base + smoothstep(frac) == coords + frac * (frac * (3 - 2 frac) - 1)
    bend = 3.0 - 2.0 * frac
    bend *= frac
    bend -= 1.0
    bend *= frac
    coords += bend
    return map_coordinates(_lattice(seed), coords, order=1, mode="grid-wrap")


# Lattice period in cells: a noise pattern repeats only every _LATTICE feature sizes.
_LATTICE = 48


@lru_cache(maxsize=128)
def _lattice(seed: int) -> np.ndarray:
    """Random lattice values [L,L,L] in [0, 1) for ``seed`` (cached; 0.9 MB each)."""
    return np.random.default_rng([int(seed) % (1 << 63), 0x7E47]).random((_LATTICE,) * 3)


@lru_cache(maxsize=1024)
def _lattice_shift(seed: int, salt: int) -> np.ndarray:
    shift = np.random.default_rng([int(seed) % (1 << 63), 0x5A17, salt]).uniform(0.0, _LATTICE, 3)
    shift.setflags(write=False)
    return shift


def texture_seed(scene_seed: int, object_index: int) -> int:
    """Per-object noise seed derived from the scene seed (stable across runs and platforms)."""
    return (int(scene_seed) * 1_000_003 + 7 * int(object_index) + 1) % (1 << 63)


