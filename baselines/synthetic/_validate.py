"""Small argument checks shared by the spec dataclasses; each error names the offending field."""
from __future__ import annotations

import math
from typing import Any, Iterable


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_float(name: str, value: Any) -> float:
    """A finite real number, returned as float."""
    if not _is_number(value) or not math.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def check_positive(name: str, value: Any) -> float:
    value = check_float(name, value)
    if value <= 0.0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return value


def check_nonnegative(name: str, value: Any) -> float:
    value = check_float(name, value)
    if value < 0.0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return value


def check_range(name: str, value: Any, low: float, high: float) -> float:
    value = check_float(name, value)
    if not low <= value <= high:
        raise ValueError(f"{name} must lie in [{low}, {high}], got {value!r}")
    return value


def check_int(name: str, value: Any, minimum: int) -> int:
    """An integer (not bool) >= minimum."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")
    return int(value)


def check_vec3(name: str, value: Any) -> tuple[float, float, float]:
    """Three finite numbers, returned as a tuple of floats."""
    if not isinstance(value, (tuple, list)) or len(value) != 3:
        raise ValueError(f"{name} must be 3 numbers, got {value!r}")
    return tuple(check_float(f"{name}[{i}]", v) for i, v in enumerate(value))  # type: ignore[return-value]


def check_direction(name: str, value: Any) -> tuple[float, float, float]:
    """A non-zero 3-vector (not normalised)."""
    vec = check_vec3(name, value)
    if math.hypot(*vec) < 1e-12:
        raise ValueError(f"{name} must be a non-zero vector, got {value!r}")
    return vec


def check_color(name: str, value: Any) -> tuple[float, float, float]:
    vec = check_vec3(name, value)
    for i, v in enumerate(vec):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{name}[{i}] must lie in [0, 1], got {v!r}")
    return vec


def check_choice(name: str, value: Any, choices: Iterable[str]) -> str:
    choices = tuple(choices)
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(choices)}; got {value!r}")
    return value


def check_name(name: str, value: Any) -> str:
    """A non-empty identifier-like string (used in file names and JSON)."""
    if not isinstance(value, str) or not value or not all(c.isalnum() or c in "_-" for c in value):
        raise ValueError(f"{name} must be a non-empty string of letters, digits, '_' or '-', "
                         f"got {value!r}")
    return value
