"""Small loaders and checks that turn malformed inputs into one `DatasetError` naming the file."""
from __future__ import annotations

import json
import math
import threading
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DatasetError

# np.load parses the .npy header with ast.literal_eval, which is not thread-safe on CPython 3.11
# before 3.11.8 ("AST constructor recursion depth mismatch", gh-106905); views load in threads.
_NPY_HEADER_LOCK = threading.Lock()


def require_file(path: Path, what: str = "file") -> Path:
    if not path.is_file():
        raise DatasetError(f"missing {what}: {path}")
    return path


def require_dir(path: Path, what: str = "folder") -> Path:
    if not path.is_dir():
        raise DatasetError(f"missing {what}: {path}")
    return path


def load_json(path: Path) -> Any:
    """Parse a JSON file; missing or malformed files raise `DatasetError` naming the file."""
    require_file(path, "JSON file")
    try:
        with open(path, "r", encoding="utf-8") as f:
            return json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"malformed JSON in {path}: {exc}") from exc


def load_npy(path: Path) -> np.ndarray:
    """Load a numeric .npy array (no pickles); malformed files raise `DatasetError` naming the file."""
    require_file(path, ".npy file")
    with open(path, "rb") as f:
        head = f.read(16)
    if not head.startswith(b"\x93NUMPY"):  # numpy would talk about pickles for any foreign file
        shown = head[:12].decode("ascii", "replace").encode("unicode_escape").decode("ascii")
        raise DatasetError(f"{path} is not a .npy file (no NumPy header; it starts with '{shown}')")
    try:
        with _NPY_HEADER_LOCK:
            array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DatasetError(f"malformed .npy file {path}: {exc}") from exc
    if not isinstance(array, np.ndarray) or not np.issubdtype(array.dtype, np.number) \
            or np.issubdtype(array.dtype, np.complexfloating):  # a cast to float would drop the imaginary part
        raise DatasetError(f"{path} does not hold a numeric array (dtype {getattr(array, 'dtype', None)})")
    return array


def require_finite(array: np.ndarray, source: Path | str, what: str) -> np.ndarray:
    """Raise `DatasetError` if `array` holds NaN or inf, naming the first bad entry."""
    array = np.asarray(array, dtype=np.float64)
    bad = ~np.isfinite(array)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise DatasetError(f"non-finite {what} in {source} at index {index}: {array[index]}")
    return array


def json_key(data: Any, key: str, source: Path, default: Any = ...) -> Any:
    """`data[key]`, or `default` when given, else a `DatasetError` naming the key and file."""
    if not isinstance(data, dict):
        raise DatasetError(f"{source}: expected a JSON object, got {type(data).__name__}")
    if key in data:
        return data[key]
    if default is not ...:
        return default
    raise DatasetError(f"{source}: missing key '{key}'")


def json_array(data: Any, key: str, source: Path, shape: tuple[int, ...] | None = None,
               default: Any = ...) -> np.ndarray:
    """A finite float64 array from `data[key]`, optionally of an exact shape."""
    value = json_key(data, key, source, default)
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{source}: key '{key}' is not numeric: {value!r}") from exc
    if shape is not None and array.shape != shape:
        raise DatasetError(f"{source}: key '{key}' has shape {array.shape}, expected {shape}")
    return require_finite(array, source, f"'{key}'")


def json_float(data: Any, key: str, source: Path, default: Any = ..., positive: bool = False) -> float:
    """`data[key]` as a finite float (DatasetError naming `source` and the key otherwise); a missing key
    gives `default` as it is (NaN included: "absent"), or an error when no default is given."""
    if default is not ... and isinstance(data, dict) and key not in data:
        return default
    value = json_key(data, key, source, default)
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{source}: key '{key}' is not a number: {value!r}") from exc
    if not math.isfinite(number):
        raise DatasetError(f"{source}: key '{key}' is not finite: {value!r}")
    if positive and number <= 0:
        raise DatasetError(f"{source}: key '{key}' must be positive, got {number}")
    return number
