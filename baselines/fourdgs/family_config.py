"""The config file a run gets when the user passes no ``--configs``: the dataset family's default.

4DGS's bare dataclass defaults (4 HexPlane levels up to 8x, 32 channels: tens of millions of plane
parameters) fit no dataset; 4DGS itself always runs with a per-family config. So when a train.py
command line has no ``--configs``, the family is detected from the dataset folder and its file is
added, in this order of precedence:

1. ``--configs none`` (or ``--configs=none``): the bare defaults, on purpose; nothing is added;
2. any other ``--configs``: the user's files, nothing is added;
3. ``--start_checkpoint`` naming an output folder: that folder's saved configuration (its
   ``config.json`` or 4DGS's ``cfg_args``, arguments/cli.py), nothing is added;
4. otherwise the family's file (``FAMILY_CONFIGS``); with exactly one plugin whose family file
   ``arguments/<family>/<plugin>.py`` exists (e.g. ``arguments/nvidia/reflow.py``), that file,
   which builds on the family default.

Families: scenes written by our simulator (a ``scene.json`` with ``simulator_version``; they also
match the NVIDIA layout) -> ``synthetic``; the detected reader otherwise (``--dataset_type``
when given): ``nvidia``, ``hypernerf``, ``dnerf``; ``colmap`` (e.g. ``baselines.prepare`` output
of a hand-held video) -> ``hypernerf``'s file, 4DGS's config for monocular real captures with a
moving camera. The choice is logged and recorded in the run's ``config.json``
(``_default_config``).

The HexPlane's temporal resolution follows the capture too (``fit_time_cells``): a family file
holds one value for its datasets' usual length (4DGS's rule of thumb, which its per-scene files
follow: about half the number of frames), so a shorter capture gets half its frame count when that
is fewer. With more cells than that, the cells around a held-out time lie between the ones the
training frames sample and get no photometric gradient: the held-out view is rendered with an
untrained deformation (NVIDIA Balloon1, 12 frames on the NVIDIA file's 96 cells: both held-out
times sat on cells still at their initial value after 1000 iterations). Only the automatic choice
is adapted; ``--configs`` and ``--kplanes_config`` keep their value.

The background colour follows the family too when neither a flag (``-w`` /
``--no-white_background``) nor a config file sets it: black for real captures (``nvidia``,
``hypernerf``, ``colmap``: white would show where nothing is reconstructed), white for ``dnerf``
(Blender renders on white) and for our ``synthetic`` scenes (the setting they were tuned with).
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("train")

CONFIG_ROOT = Path(__file__).resolve().parents[2] / "arguments"
BARE_DEFAULTS = "none"
# family -> its default config, relative to arguments/
FAMILY_CONFIGS = {
    "synthetic": "synthetic/default.py",
    "nvidia": "nvidia/default.py",
    "hypernerf": "hypernerf/default.py",
    "dnerf": "dnerf/dnerf_default.py",
    "colmap": "hypernerf/default.py",
    "panoptic": "hypernerf/default.py",
}


WHITE_BACKGROUND = {"synthetic": True, "dnerf": True, "nvidia": False, "hypernerf": False, "colmap": False,
                    "panoptic": False}


def family_background(family: str) -> bool | None:
    """Whether the family's renders use a white background (None: unknown family, keep the default)."""
    return WHITE_BACKGROUND.get(family)


@dataclass
class DefaultConfig:
    """What was decided for a command line without ``--configs`` (or with ``--configs none``)."""

    path: Path | None  # None: the bare defaults
    family: str | None
    reason: str

    def as_dict(self) -> dict:
        return {"path": str(self.path) if self.path else None, "family": self.family, "reason": self.reason}


MIN_TIME_CELLS = 2  # bilinear sampling along time needs two cells


def fit_time_cells(config_cells: int, num_times: int) -> int:
    """The temporal resolution for a capture of ``num_times`` distinct frame times: the config's
    ``config_cells``, lowered to half the frame count (rounded up, at least ``MIN_TIME_CELLS``) when
    that is fewer (see the module docstring)."""
    return min(int(config_cells), max(MIN_TIME_CELLS, -(-int(num_times) // 2)))


def is_simulator_scene(source: Path) -> bool:
    """Whether ``source`` was written by ``baselines.synthetic`` (its scene.json names the simulator)."""
    path = source / "scene.json"
    if not path.is_file():
        return False
    try:
        return "simulator_version" in json.loads(path.read_text())
    except (OSError, ValueError):
        return False


def dataset_family(source: Path, dataset_type: str = "auto") -> str:
    """``synthetic``, or the reader kind (``--dataset_type``, else detected from the files)."""
    from baselines.data.detection import detect_layout

    if is_simulator_scene(source):
        return "synthetic"
    return dataset_type if dataset_type != "auto" else detect_layout(source, warn=False).kind


def default_config(source: Path, plugins: list[str], dataset_type: str = "auto",
                   family: str | None = None) -> DefaultConfig:
    """The family config for a command line without ``--configs`` (rule: module docstring).

    ``family`` skips detection (the embedded scene is known to be ``synthetic`` before it exists).
    """
    family = family or dataset_family(source, dataset_type)
    relative = FAMILY_CONFIGS.get(family)
    if relative is None:
        return DefaultConfig(None, family, f"no default config for the {family} family: 4DGS's bare defaults")
    folder = CONFIG_ROOT / Path(relative).parent
    path = CONFIG_ROOT / relative
    if len(plugins) == 1 and (folder / f"{plugins[0]}.py").is_file():
        path = folder / f"{plugins[0]}.py"
    return DefaultConfig(path, family, f"no --configs given; {family} family detected in {source}")


def strip_bare_defaults(argv: list[str]) -> tuple[list[str], bool]:
    """``argv`` without ``--configs none``, and whether it was there (then no family config is added)."""
    out, bare, skip = [], False, False
    for i, arg in enumerate(argv):
        if skip:
            skip = False
        elif arg.lower() == f"--configs={BARE_DEFAULTS}":
            bare = True
        elif arg == "--configs" and i + 1 < len(argv) and argv[i + 1].lower() == BARE_DEFAULTS:
            bare, skip = True, True
        else:
            out.append(arg)
    return out, bare


def log_decision(decision: DefaultConfig) -> None:
    if decision.path is not None:
        log.info("config: %s (%s; pass --configs FILE, or --configs none for 4DGS's bare defaults)",
                 decision.path.relative_to(CONFIG_ROOT.parent), decision.reason)
    else:
        log.warning("config: %s", decision.reason)
