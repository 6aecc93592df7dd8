"""`load_scene`: pick the reader from the files present (or the given type) and run it."""
from __future__ import annotations

import inspect
import logging
from pathlib import Path
from typing import Callable

from .colmap import find_model_dir, read_colmap
from .dnerf import read_dnerf
from .errors import DatasetError
from .hypernerf import read_hypernerf
from .nvidia import read_nvidia
from .scene_info import SceneInfo

log = logging.getLogger(__name__)

READERS: dict[str, Callable[..., SceneInfo]] = {
    "nvidia": read_nvidia,
    "dnerf": read_dnerf,
    "hypernerf": read_hypernerf,
    "colmap": read_colmap,
}
_COMMON_ARGUMENTS = ("source_path", "images", "resolution", "eval", "white_background", "llffhold")
ALIASES = {"llff": "nvidia", "dynamicnerf": "nvidia", "blender": "dnerf", "nerfies": "hypernerf"}

# What identifies each layout, in the order tried: the first match wins. poses_bounds.npy comes
# before sparse/ because LLFF-style scenes often keep the COLMAP model they were posed with.
SIGNATURES = (
    ("hypernerf", "dataset.json + scene.json", lambda p: (p / "dataset.json").is_file() and (p / "scene.json").is_file()),
    ("dnerf", "transforms_train.json", lambda p: (p / "transforms_train.json").is_file()),
    ("nvidia", "poses_bounds.npy", lambda p: (p / "poses_bounds.npy").is_file()),
    ("colmap", "sparse/0/cameras.{bin,txt}", lambda p: find_model_dir(p) is not None),
)


def detect_dataset_type(source_path: Path | str) -> str:
    """The layout of `source_path`; `DatasetError` listing what was looked for when none matches."""
    source = Path(source_path)
    if not source.is_dir():
        raise DatasetError(f"dataset folder not found: {source}")
    for name, _, matches in SIGNATURES:
        if matches(source):
            return name
    looked_for = "; ".join(f"{what} ({name})" for name, what, _ in SIGNATURES)
    raise DatasetError(f"{source} matches no known dataset layout; looked for: {looked_for}")


def _check_arguments(resolution: int | float, llffhold: int) -> None:
    """Reject bad arguments before any file is read."""
    if isinstance(resolution, bool) or not isinstance(resolution, (int, float)) or not (
            resolution == -1 or resolution > 0):
        raise DatasetError(f"resolution={resolution!r}: expected 1, 2, 4, 8, -1 or a positive width")
    if isinstance(llffhold, bool) or not isinstance(llffhold, int) or llffhold < 1:
        raise DatasetError(f"llffhold={llffhold!r}: must be a positive integer")


def load_scene(source_path: Path | str, dataset_type: str | None = "auto", images: str = "images",
               resolution: int | float = -1, eval: bool = False, white_background: bool = False,
               llffhold: int = 8, reader_options: dict | None = None) -> SceneInfo:
    """Load a dynamic scene into cameras in our convention (see `baselines/data/__init__.py`).

    Args:
        source_path: dataset folder.
        dataset_type: "auto" (or None) to detect, else one of nvidia, dnerf, hypernerf, colmap
            (aliases: llff, blender, nerfies).
        images: image folder name for nvidia/colmap (e.g. "images_2").
        resolution: 1, 2, 4, 8 = downscale factor; -1 = original unless wider than 1600 px;
            another positive value = target width (3DGS's rule).
        eval: hold out test views (nvidia/colmap: every `llffhold`-th; dnerf: transforms_test).
        white_background: composite RGBA images on white instead of black.
        llffhold: hold-out period for nvidia/colmap.
        reader_options: extra keyword arguments of the chosen reader, e.g.
            {"apply_scene_transform": False} for hypernerf (see `read_hypernerf`).
    """
    source = Path(source_path)
    _check_arguments(resolution, llffhold)
    if dataset_type is None or dataset_type == "auto":
        kind = detect_dataset_type(source)
        log.info("detected %s dataset in %s", kind, source)
    else:
        kind = ALIASES.get(str(dataset_type).lower(), str(dataset_type).lower())
        if kind not in READERS:
            raise DatasetError(f"unknown dataset_type={dataset_type!r}; expected auto, "
                               f"{', '.join(READERS)} (aliases: {', '.join(ALIASES)})")
        if not source.is_dir():
            raise DatasetError(f"dataset folder not found: {source}")
    reader = READERS[kind]
    options = dict(reader_options or {})
    accepted = set(inspect.signature(reader).parameters) - set(_COMMON_ARGUMENTS)
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise DatasetError(f"reader_options {unknown} are not options of the {kind} reader "
                           f"(it accepts: {', '.join(sorted(accepted)) or 'none'})")
    return reader(source, images=images, resolution=resolution, eval=eval,
                  white_background=white_background, llffhold=llffhold, **options)
