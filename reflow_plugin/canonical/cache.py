"""Cache of the canonical space, keyed by the dataset, the masks and every setting it depends on.

    key = cache_key(cameras, masks, provider.key(), settings)
    space = load(cache_dir, key)       # None on a miss (or an unreadable file)
    store(cache_dir, key, arrays, report)

One file per key, `<cache_dir>/space_<key>.npz` (points, colours, reference frame and the JSON
report), written atomically (temporary file + os.replace): a killed run leaves no torn file.
Another dataset, other masks or other provider/alignment settings give another key (a miss).
"""
from __future__ import annotations

import hashlib
import io
import json
import logging
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from baselines.data import Camera
from baselines.synthetic.writer import write_bytes

from ..labels import _cache_key as camera_key

log = logging.getLogger(__name__)
CACHE_VERSION = 1
ARRAYS = ("static_points", "static_colors", "dynamic_points", "dynamic_colors")


def cache_key(cameras: Sequence[Camera], masks: Sequence[np.ndarray] | None, provider_key: str,
              settings: Mapping[str, Any]) -> str:
    """16 hex digits of sha256 over cameras (poses, images, disparity), masks, provider and settings."""
    text = json.dumps(dict(settings), sort_keys=True)
    h = hashlib.sha256(f"canonical v{CACHE_VERSION}|{provider_key}|{text}".encode())
    h.update(camera_key(cameras, False).encode())
    for cam in cameras:  # the depth provider reads the (possibly corrected) disparity
        if cam.disparity is not None:
            h.update(np.ascontiguousarray(cam.disparity.detach().cpu().numpy().astype(np.float32)[::4, ::4]).tobytes())
    for mask in masks or []:
        h.update(np.packbits(np.asarray(mask, bool)).tobytes())
    return h.hexdigest()[:16]


def path_for(cache_dir: Path, key: str) -> Path:
    return Path(cache_dir) / f"space_{key}.npz"


def load(cache_dir: Path | None, key: str) -> tuple[dict[str, np.ndarray], int | None, dict] | None:
    """(arrays, reference frame, report) of a stored space, or None."""
    if cache_dir is None or not path_for(cache_dir, key).is_file():
        return None
    try:
        with np.load(path_for(cache_dir, key), allow_pickle=False) as data:
            arrays = {name: data[name] for name in ARRAYS}
            reference = int(data["reference"])
            report = json.loads(str(data["report"]))
    except (OSError, KeyError, ValueError) as exc:
        log.warning("canonical cache %s unreadable (%s); recomputing", path_for(cache_dir, key), exc)
        return None
    return arrays, (None if reference < 0 else reference), report


def store(cache_dir: Path | None, key: str, arrays: Mapping[str, np.ndarray], reference: int | None,
          report: Mapping[str, Any]) -> None:
    if cache_dir is None:
        return
    buffer = io.BytesIO()
    np.savez(buffer, **{k: np.asarray(arrays[k], np.float32) for k in ARRAYS},
             reference=np.int64(-1 if reference is None else reference), report=np.array(json.dumps(report)))
    write_bytes(path_for(cache_dir, key), buffer.getvalue())
