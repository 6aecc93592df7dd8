"""`load_scene`: pick the reader from the files present (or the given type) and run it."""
from __future__ import annotations

import inspect
import logging
from pathlib import Path
from typing import Callable

from .colmap import read_colmap
from .detection import detect_layout
from .dnerf import read_dnerf
from .errors import DatasetError
from .hypernerf import read_hypernerf
from .nvidia import POSES_FILE, check_poses_bounds, read_nvidia
from .panoptic import read_panoptic
from .scene_info import SceneInfo
from .split_check import warn_split_overlap

log = logging.getLogger(__name__)

READERS: dict[str, Callable[..., SceneInfo]] = {
    "nvidia": read_nvidia,
    "dnerf": read_dnerf,
    "hypernerf": read_hypernerf,
    "colmap": read_colmap,
    "panoptic": read_panoptic,
}
_COMMON_ARGUMENTS = ("source_path", "images", "resolution", "eval", "white_background", "llffhold")
# Common arguments a reader does not read (its layout fixes them): a value the user changed is
# warned about instead of silently dropped. HyperNeRF always uses the dataset's own split.
IGNORED_ARGUMENTS = {"hypernerf": ("images", "eval", "llffhold"), "dnerf": ("images", "llffhold"),
                     "panoptic": ("images", "llffhold")}
# flag and default of each; --eval's default is True (4DGS's), so the one to warn about is --no-eval
_ARGUMENT_FLAGS = {"images": ("-i/--images", "images"), "llffhold": ("--llffhold", 8), "eval": ("--no-eval", True)}

# "synthetic": baselines.synthetic writes the NVIDIA layout (its family config is chosen from the name)
ALIASES = {"llff": "nvidia", "dynamicnerf": "nvidia", "synthetic": "nvidia", "blender": "dnerf", "nerfies": "hypernerf"}

def detect_dataset_type(source_path: Path | str) -> str:
    """The layout of `source_path` (see detection.py for the preference rule)."""
    return detect_layout(source_path).kind


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
        dataset_type: "auto" (or None) to detect, else one of nvidia, dnerf, hypernerf, colmap,
            panoptic (aliases: llff, blender, nerfies).
        images: image folder name for nvidia/colmap (e.g. "images_2").
        resolution: 1, 2, 4, 8 = downscale factor; -1 = original unless wider than 1600 px;
            another positive value = target width (3DGS's rule).
        eval: hold out test views (nvidia/colmap: every `llffhold`-th; dnerf: transforms_test).
        white_background: composite RGBA images on white instead of black.
        llffhold: hold-out period for nvidia/colmap.
        reader_options: extra keyword arguments of the chosen reader, e.g.
            {"apply_scene_transform": False} for hypernerf (see `read_hypernerf`), or
            {"train_cameras": [12, 18], "test_every": 10} for panoptic (see `read_panoptic`).
    """
    source = Path(source_path)
    _check_arguments(resolution, llffhold)
    detection = None
    if dataset_type is None or dataset_type == "auto":
        detection = detect_layout(source)
        kind = detection.kind
        log.info("detected %s dataset in %s", kind, source)
    else:
        kind = ALIASES.get(str(dataset_type).lower(), str(dataset_type).lower())
        if kind not in READERS:
            raise DatasetError(f"unknown dataset_type={dataset_type!r}; expected auto, "
                               f"{', '.join(READERS)} (aliases: {', '.join(ALIASES)})")
        if not source.is_dir():
            raise DatasetError(f"-s {source}: is a file; -s names the dataset folder (the one holding images/ or "
                           "poses_bounds.npy ...)" if source.is_file() else f"dataset folder not found: {source}")
    reader = READERS[kind]
    options = dict(reader_options or {})
    accepted = set(inspect.signature(reader).parameters) - set(_COMMON_ARGUMENTS)
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise DatasetError(f"reader_options {unknown} are not options of the {kind} reader "
                           f"(it accepts: {', '.join(sorted(accepted)) or 'none'})")
    if kind != "nvidia" and (source / POSES_FILE).is_file():
        check_poses_bounds(source, images)  # a NaN there must not pass unnoticed, whatever reads the folder
    for name, value in (("images", images), ("llffhold", llffhold), ("eval", eval)):
        flag, default = _ARGUMENT_FLAGS[name]
        if name in IGNORED_ARGUMENTS.get(kind, ()) and value != default:
            given = flag if name == "eval" else f"{flag} {value}"
            log.warning("%s is not read by the %s reader (its layout fixes it)", given, kind)
    scene = reader(source, images=images, resolution=resolution, eval=eval,
                   white_background=white_background, llffhold=llffhold, **options)
    chosen = detection.as_dict() if detection else {"picked": kind, "because": "--dataset_type"}
    scene.metadata["layout_detection"] = chosen
    warn_split_overlap(scene)
    return scene
