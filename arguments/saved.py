"""A run's saved configuration: 4DGS's ``cfg_args`` and our ``config.json``.

``write_cfg_args(model_dir, train_args)`` writes, atomically,

- ``cfg_args``: 4DGS's format, ``repr(argparse.Namespace(...))`` of every field of every group,
  flattened (4DGS tools and ``render.py`` read it with ``eval``);
- ``config.json``: one object per group (``ModelParams``, ..., plugin groups, ``RunParams``),
  in the config-file format, so ``--configs <model_dir>/config.json`` reproduces the run;
  keys starting with ``_`` (ignored by the loader) record the sources of values and the
  command line.

``read_saved_config`` reads ``config.json`` when present, else ``cfg_args`` (so 4DGS output
directories work too).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .config import validate_file
from .fields import as_dict, split_comma_list
from .layers import ConfigError, Layer, Schema, field_owner

if TYPE_CHECKING:
    from .cli import TrainArgs

log = logging.getLogger("arguments")

CFG_ARGS = "cfg_args"
CONFIG_JSON = "config.json"
_CLI_ONLY_FIELDS = {"configs", "overwrite"}  # never replayed from a saved config


def write_cfg_args(path: str | Path, train_args: TrainArgs,
                   facts: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """Write ``<path>/cfg_args`` and ``<path>/config.json`` atomically; returns both paths.

    ``path`` is the model directory (created if missing). ``facts``: extra top-level entries of
    config.json about the run (e.g. ``_components``, the plugins' resolved components); their
    keys start with "_" so that the file still loads as a config layer.
    """
    model_dir = Path(path)
    model_dir.mkdir(parents=True, exist_ok=True)
    groups = {name: as_dict(inst) for name, inst in train_args.groups().items()}
    flat: dict[str, Any] = {}
    for values in groups.values():
        flat.update(values)
    cfg_path = model_dir / CFG_ARGS
    atomic_write_text(cfg_path, repr(argparse.Namespace(**flat)))
    doc: dict[str, Any] = {
        "_about": "Resolved configuration of this run; reuse with --configs <this file>.",
        "_argv": list(train_args.argv),
        "_configs": list(train_args.run.configs),
        "_sources": dict(train_args.sources),
    }
    for key, value in (facts or {}).items():
        if not key.startswith("_"):
            raise ValueError(f"write_cfg_args: fact {key!r} must start with '_' (config.json is also a config file)")
        doc[key] = value
    for name, values in groups.items():
        if name == "RunParams":
            values = {k: v for k, v in values.items() if k not in _CLI_ONLY_FIELDS}
        doc[name] = values
    json_path = model_dir / CONFIG_JSON
    atomic_write_text(json_path, json.dumps(doc, indent=2) + "\n")
    return cfg_path, json_path


def read_saved_config(model_dir: str | Path, schema: Schema) -> Layer:
    """The saved configuration of a model directory as a layer (empty, with a warning, when
    the directory has neither file). Groups and fields unknown to ``schema`` (e.g. of a plugin
    not loaded now, or 4DGS run-level keys) are skipped, since the file describes a past run.

    Raises ConfigError when the directory is missing or a file is unreadable.
    """
    model_dir = Path(model_dir).expanduser()
    if not model_dir.is_dir():
        raise ConfigError(f"{model_dir}: model directory not found (-m/--model_path)",
                          file=str(model_dir), key="model_path")
    json_path, cfg_path = model_dir / CONFIG_JSON, model_dir / CFG_ARGS
    if json_path.is_file():
        return _read_config_json(json_path, schema)
    if cfg_path.is_file():
        return _read_cfg_args(cfg_path, schema)
    log.warning("%s: no %s or %s found; using defaults, config files and the command line only",
                model_dir, CONFIG_JSON, CFG_ARGS)
    return Layer()


MODEL_GROUPS = ("ModelHiddenParams",)  # the architecture; plus ModelParams.sh_degree
MODEL_FIELDS = {"ModelParams": ("sh_degree",)}


def model_dir_of_checkpoint(start_checkpoint: str | Path | None) -> Path | None:
    """The model directory behind ``--start_checkpoint`` when it names a folder, else None.

    ``OLD/point_cloud/iteration_N`` (a folder holding ``point_cloud.ply``) -> ``OLD``; ``OLD``
    itself otherwise. No checkpoint or a ``chkpnt_*.pth`` file gives None (its run's flags are the user's).
    """
    if not start_checkpoint:
        return None
    path = Path(start_checkpoint).expanduser()
    if not path.is_dir():
        return None
    return path.parent.parent if (path / "point_cloud.ply").is_file() else path


def read_saved_model_config(model_dir: str | Path, schema: Schema) -> Layer:
    """The model hyperparameters (``ModelHiddenParams``, ``sh_degree``) of a saved run, as a layer.

    What ``render.py -m`` reads, restricted to what fixes the shapes of a trained model, so a run
    continuing from an old output (ours or 4DGS's) builds a model its files fit.
    """
    saved = read_saved_config(model_dir, schema)
    kept = Layer()
    for group, names in saved.values.items():
        for name, value in names.items():
            if group in MODEL_GROUPS or name in MODEL_FIELDS.get(group, ()):
                kept.set(group, name, value, saved.sources[(group, name)])
    return kept


def read_saved_configs(model_dir: str | Path) -> list[str]:
    """The ``--configs`` a saved run was trained with ([] when it recorded none)."""
    model_dir = Path(model_dir).expanduser()
    json_path, cfg_path = model_dir / CONFIG_JSON, model_dir / CFG_ARGS
    if json_path.is_file():
        value = _load_json(json_path).get("_configs", [])
    elif cfg_path.is_file():
        value = _eval_cfg_args(cfg_path).get("configs", [])
    else:
        return []
    return split_comma_list([value] if isinstance(value, str) else list(value))


def read_saved_plugins(model_dir: str | Path) -> list[str]:
    """``RunParams.plugin`` of a model directory's saved configuration ([] when none)."""
    model_dir = Path(model_dir).expanduser()
    json_path, cfg_path = model_dir / CONFIG_JSON, model_dir / CFG_ARGS
    if json_path.is_file():
        value = _load_json(json_path).get("RunParams", {}).get("plugin", [])
    elif cfg_path.is_file():
        value = _eval_cfg_args(cfg_path).get("plugin", [])
    else:
        return []
    return split_comma_list([value] if isinstance(value, str) else list(value))


def _read_config_json(path: Path, schema: Schema) -> Layer:
    raw = _load_json(path)
    kept: dict[str, dict[str, Any]] = {}
    for group, entries in raw.items():
        if group.startswith("_"):
            continue
        if group not in schema or not isinstance(entries, dict):
            log.warning("%s: saved group %s skipped (its plugin is not loaded)", path, group)
            continue
        kept[group] = {k: v for k, v in entries.items() if k in schema[group]}
    return validate_file(path, kept, schema)


def _read_cfg_args(path: Path, schema: Schema) -> Layer:
    flat = _eval_cfg_args(path)
    grouped: dict[str, dict[str, Any]] = {}
    for name, value in flat.items():
        owner = field_owner(schema, name)
        if owner is None or name in _CLI_ONLY_FIELDS:
            continue  # 4DGS writes run-level keys (configs, ...) we have no field for
        grouped.setdefault(owner, {})[name] = value
    return validate_file(path, grouped, schema)


def _load_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ConfigError(f"{path}:{err.lineno}: invalid JSON: {err.msg}", file=str(path)) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected an object of groups", file=str(path))
    return data


def _eval_cfg_args(path: Path) -> dict[str, Any]:
    text = path.read_text(encoding="utf-8")
    try:
        # cfg_args holds only literals inside Namespace(...): evaluate with nothing else in scope
        ns = eval(text, {"__builtins__": {}, "Namespace": argparse.Namespace}, {})  # noqa: S307
    except Exception as err:
        raise ConfigError(f"{path}: unreadable cfg_args ({type(err).__name__}: {err})",
                          file=str(path)) from None
    if not isinstance(ns, argparse.Namespace):
        raise ConfigError(f"{path}: expected Namespace(...), got {type(ns).__name__}",
                          file=str(path))
    return vars(ns)


def atomic_write_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
