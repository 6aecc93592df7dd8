"""Which reader a dataset folder gets: every layout signature is tested, the strongest match wins.

Real folders often carry several layouts' files side by side (an NVIDIA capture converted for
other codebases keeps ``poses_bounds.npy`` + ``images/`` next to ``dataset.json`` and Blender-style
``transforms_*.json``). Preference rule, strongest first:

1. ``nvidia``: ``poses_bounds.npy`` next to an image folder (``images*/``): per-frame calibrated
   poses beside the very images they belong to, the NVIDIA/LLFF family's own files;
2. ``hypernerf``: ``dataset.json`` + ``scene.json``;
3. ``dnerf``: ``transforms_train.json``;
4. ``panoptic``: ``train_meta.json`` + ``ims/`` (CMU Panoptic in the Dynamic3DGaussians layout);
5. ``nvidia``: ``poses_bounds.npy`` alone (the reader then names the missing image folder);
6. ``colmap``: ``sparse/0/cameras.{bin,txt}`` (last: LLFF-style scenes keep the COLMAP model they
   were posed with).

A COLMAP model beside ``poses_bounds.npy`` is no competing layout: LLFF poses come from it, and the
nvidia reader reads it as its point file. When more than one layout matches otherwise, the choice,
the reason and the other matches are logged as one warning and recorded (``Detection.as_dict``, saved in the run's ``config.json``);
``--dataset_type`` overrides.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from .colmap import find_model_dir
from .errors import DatasetError

log = logging.getLogger(__name__)


def _has_image_folder(path: Path) -> bool:
    return any(p.is_dir() for p in path.glob("images*"))


SIGNATURES: tuple[tuple[str, str, Callable[[Path], bool]], ...] = (
    ("nvidia", "poses_bounds.npy + images*/",
     lambda p: (p / "poses_bounds.npy").is_file() and _has_image_folder(p)),
    ("hypernerf", "dataset.json + scene.json",
     lambda p: (p / "dataset.json").is_file() and (p / "scene.json").is_file()),
    ("dnerf", "transforms_train.json", lambda p: (p / "transforms_train.json").is_file()),
    ("panoptic", "train_meta.json + ims/", lambda p: (p / "train_meta.json").is_file() and (p / "ims").is_dir()),
    ("nvidia", "poses_bounds.npy", lambda p: (p / "poses_bounds.npy").is_file()),
    ("colmap", "sparse/0/cameras.{bin,txt}", lambda p: find_model_dir(p) is not None),
)
# (picked, other): the other layout's files belong to the picked one (see the module docstring)
COMPANIONS = {("nvidia", "colmap")}


@dataclass
class Detection:
    """The chosen layout, the files that decided it, and the other layouts that matched."""

    kind: str
    signature: str
    also_matched: list[tuple[str, str]] = field(default_factory=list)  # (kind, signature)

    @property
    def ambiguous(self) -> bool:
        return bool(self.also_matched)

    def describe(self) -> str:
        others = ", ".join(f"{kind} ({what})" for kind, what in self.also_matched)
        return (f"picked {self.kind} because of {self.signature} (the stronger signal by the documented "
                f"preference rule); also matched: {others}; pass --dataset_type to choose another")

    def as_dict(self) -> dict:
        return {"picked": self.kind, "because": self.signature,
                "also_matched": [{"type": k, "files": w} for k, w in self.also_matched]}


def detect_layout(source_path: Path | str, warn: bool = True) -> Detection:
    """The layout of ``source_path`` by the preference rule; ``DatasetError`` when none matches.

    ``warn=False`` for callers that only need the kind (the reader warns about ambiguity once).
    """
    source = Path(source_path)
    if not source.is_dir():
        raise DatasetError(f"-s {source}: is a file; -s names the dataset folder (the one holding images/ or "
                           "poses_bounds.npy ...)" if source.is_file() else f"dataset folder not found: {source}")
    matched = [(kind, what) for kind, what, matches in SIGNATURES if matches(source)]
    if not matched:
        looked_for = "; ".join(f"{what} ({kind})" for kind, what, _ in SIGNATURES)
        raise DatasetError(f"{source} matches no known dataset layout; looked for: {looked_for}")
    kind, what = matched[0]
    # nvidia's weaker signature is no other layout, nor a companion's files
    others = [(k, w) for k, w in matched[1:] if k != kind and (kind, k) not in COMPANIONS]
    detection = Detection(kind, what, others)
    if warn and detection.ambiguous:
        log.warning("%s: several dataset layouts match: %s", source, detection.describe())
    return detection
