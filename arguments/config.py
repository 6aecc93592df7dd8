"""4DGS-style config files: Python (or JSON) files of dicts, one per parameter group.

A config file looks like 4DGS's ``arguments/<dataset>/*.py``::

    _base_ = './default.py'                  # optional; a str or a list, relative to this file
    ModelHiddenParams = dict(
        kplanes_config={'resolution': [64, 64, 64, 75]},   # merges into the base's dict
        multires=[1, 2],
    )
    OptimizationParams = dict(iterations=20_000)

Precedence (lowest to highest)
------------------------------
1. the dataclass defaults (4DGS's values, see ``arguments/params.py``);
2. config files, in ``--configs`` order; each file is applied after its ``_base_`` chain (bases
   in list order, each after its own bases), so a file overrides its bases and a later
   ``--configs`` file overrides an earlier one;
3. flags typed on the command line (only those typed: argparse defaults never override a
   config value).

(For ``render.py`` the saved configuration of the model directory sits between 1 and 2.)
Dict-valued fields (``kplanes_config``) merge key by key, recursively, at every level,
including onto the defaults, so a file may set only ``{'resolution': [...]}``; a dict containing
``_delete_=True`` replaces instead of merging (as in mmcv). A group dict with ``_delete_=True``
discards what lower levels set for that group. Lists and all other values are replaced.
This differs from 4DGS, where the config file overrides the command line.

Rules
-----
- Top-level names are group names: ``ModelParams``, ``PipelineParams``, ``OptimizationParams``,
  ``ModelHiddenParams``, ``RunParams`` (train.py-level flags, ours) and groups registered by
  loaded plugins. Names starting with ``_`` and imported modules are ignored (helpers).
- As in 4DGS, which flattens all groups into one namespace, a field placed under another group
  (4DGS's own files put ``render_process`` under ``OptimizationParams``) is applied to the group
  that defines it, with a warning.
- Values are type-checked per file; lossless conversions (int -> float, integral float -> int,
  tuple -> list) are applied.
- Every problem raises one ``ConfigError`` naming the file and the key: missing file, syntax or
  execution error (with the line), unknown group, unknown field, wrong type, ``_base_`` cycle or
  missing base.
- Config files are executed as Python, like 4DGS's (mmcv) config files: use trusted files only.
"""
from __future__ import annotations

import json
import logging
import traceback
import types
from pathlib import Path
from typing import Any

from .fields import CoercionError, coerce
from .layers import DELETE, ConfigError, Layer, Schema, close_matches, field_owner, merge_layers, removed_note

log = logging.getLogger("arguments")

BASE_KEY = "_base_"
# RunParams fields that only make sense on the command line (overwrite: a run folder is cleared only
# when the user types it; the folder check reads the typed flag).
_CLI_ONLY = {("RunParams", "configs"), ("RunParams", "overwrite")}


def read_config_chain(path: str | Path, *, referrer: str = "--configs") -> list[tuple[Path, dict]]:
    """The raw top-level dicts of ``path`` and its ``_base_`` chain, in application order
    (bases first, ``path`` last). No schema validation: see :func:`load_config`.

    ``referrer`` says where ``path`` was named, for the missing-file error.
    """
    return _read_chain(Path(path).expanduser(), referrer, ())


def _read_chain(path: Path, referrer: str, stack: tuple[Path, ...]) -> list[tuple[Path, dict]]:
    path = path.resolve()
    if path in stack:
        cycle = " -> ".join(str(p) for p in (*stack[stack.index(path):], path))
        raise ConfigError(f"{stack[-1]}: {BASE_KEY} cycle: {cycle}", file=str(stack[-1]),
                          key=BASE_KEY)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found ({referrer})", file=str(path),
                          key=BASE_KEY if stack else None)
    raw = _execute(path)
    bases = raw.pop(BASE_KEY, [])
    if isinstance(bases, str):
        bases = [bases]
    if not isinstance(bases, (list, tuple)) or not all(isinstance(b, str) for b in bases):
        raise ConfigError(f"{path}: {BASE_KEY} must be a path or a list of paths, got {bases!r}",
                          file=str(path), key=BASE_KEY)
    chain: list[tuple[Path, dict]] = []
    for base in bases:
        base_path = (path.parent / Path(base).expanduser())
        chain += _read_chain(base_path, f"{BASE_KEY} {base!r} of {path}", (*stack, path))
    chain.append((path, raw))
    return chain


def _execute(path: Path) -> dict[str, Any]:
    """Top-level names of a config file (JSON object, or the globals a Python file defines)."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ConfigError(f"{path}:{err.lineno}: invalid JSON: {err.msg}", file=str(path),
                              key=None) from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: top level must be an object of groups", file=str(path))
        return {k: v for k, v in data.items() if not (k.startswith("_") and k != BASE_KEY)}
    try:
        code = compile(text, str(path), "exec")
    except SyntaxError as err:
        raise ConfigError(f"{path}:{err.lineno}: syntax error: {err.msg}", file=str(path),
                          key=None) from None
    namespace: dict[str, Any] = {"__file__": str(path), "__name__": "__config__"}
    try:
        exec(code, namespace)  # noqa: S102 - config files are trusted Python, as in 4DGS
    except Exception as err:  # any error in user code becomes one ConfigError with the line
        lines = [f.lineno for f in traceback.extract_tb(err.__traceback__)
                 if f.filename == str(path)]
        where = f"{path}:{lines[-1]}" if lines else str(path)
        raise ConfigError(f"{where}: error while executing: {type(err).__name__}: {err}",
                          file=str(path)) from None
    return {k: v for k, v in namespace.items()
            if not (k.startswith("_") and k != BASE_KEY)
            and not isinstance(v, (types.ModuleType, types.FunctionType, type))}


def validate_file(path: Path, raw: dict[str, Any], schema: Schema) -> Layer:
    """Check one file's groups, fields and value types against ``schema``; return its layer.

    Fields placed under another group than the one defining them are moved there (4DGS
    flattens groups) with a warning.
    """
    src = str(path)
    layer = Layer()
    known_groups = list(schema)
    for group, entries in raw.items():
        if group not in schema:
            hint = close_matches(group, known_groups)
            raise ConfigError(
                f"{src}: unknown group '{group}'"
                + (f" (did you mean {' or '.join(repr(h) for h in hint)}?)" if hint else "")
                + f"; known groups: {', '.join(known_groups)}. Plugin groups exist only when the "
                  "plugin is loaded (--plugin NAME).", file=src, key=group)
        if not isinstance(entries, dict):
            raise ConfigError(f"{src}: group '{group}' must be a dict of field -> value, got "
                              f"{type(entries).__name__}", file=src, key=group)
        for name, value in entries.items():
            key = f"{group}.{name}"
            if name == DELETE:
                if not isinstance(value, bool):
                    raise ConfigError(f"{src}: {key} must be True or False", file=src, key=key)
                layer.values.setdefault(group, {})[DELETE] = value
                continue
            owner = group if name in schema[group] else field_owner(schema, name)
            if owner is None:
                note = removed_note(schema, str(name))
                if note:
                    raise ConfigError(f"{src}: {note}; delete the key", file=src, key=key)
                all_fields = [f for specs in schema.values() for f in specs]
                hint = close_matches(str(name), list(schema[group]) + all_fields)
                raise ConfigError(
                    f"{src}: unknown field '{key}'"
                    + (f" (did you mean {' or '.join(repr(h) for h in dict.fromkeys(hint))}?)"
                       if hint else ""), file=src, key=key)
            if (owner, name) in _CLI_ONLY:
                use = f"use {BASE_KEY} to include other files" if name == "configs" else f"type --{name}"
                raise ConfigError(f"{src}: {owner}.{name} cannot be set in a config file ({use})",
                                  file=src, key=key)
            if owner != group:
                if (owner, name) in layer.sources:
                    raise ConfigError(f"{src}: '{name}' is given under both {group} and "
                                      f"{owner}", file=src, key=key)
                log.info("%s: %s is a field of %s; applied there (4DGS merges all groups "
                         "into one namespace)", src, key, owner)
            elif (owner, name) in layer.sources:
                raise ConfigError(f"{src}: '{name}' is given under both {group} and another "
                                  "group", file=src, key=key)
            spec = schema[owner][name]
            try:
                value = coerce(spec, value)
            except CoercionError as err:
                raise ConfigError(f"{src}: {spec.qualname}: {err}", file=src,
                                  key=spec.qualname) from None
            # dict fields are checked once merged (a file may give only some keys)
            problem = spec.check(value) if spec.check and spec.kind != "dict" else None
            if problem:
                raise ConfigError(f"{src}: {spec.qualname}: {problem}", file=src,
                                  key=spec.qualname)
            layer.set(owner, name, value, src)
    return layer


def load_config(path: str | Path, schema: Schema, *, referrer: str = "--configs") -> Layer:
    """The layer of one config file with its ``_base_`` chain applied (bases first)."""
    out = Layer()
    for file_path, raw in read_config_chain(path, referrer=referrer):
        out = merge_layers(out, validate_file(file_path, raw, schema))
    return out


def load_configs(paths: list[str], schema: Schema) -> Layer:
    """The merged layer of several config files, in order (later files win)."""
    out = Layer()
    for p in paths:
        out = merge_layers(out, load_config(p, schema))
    return out
