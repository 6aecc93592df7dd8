"""Layers of parameter values and their resolution into parameter-group instances.

A *layer* is what one source contributes (a config file with its ``_base_`` chain, the command
line, a saved run configuration): ``{group: {field: value}}`` plus, for every value, the source
that set it (a file path or "command line"), so errors and warnings can name it. Layers are merged
bottom-up; dict-valued fields merge key by key, recursively, unless the upper dict carries
``_delete_=True`` (then it replaces everything below it, dataclass defaults included). A group dict
carrying ``_delete_=True`` discards what lower layers set for that group.
"""
from __future__ import annotations

import copy
import difflib
import logging
from dataclasses import dataclass, field
from typing import Any

from .fields import FieldSpec, group_fields

log = logging.getLogger("arguments")

DELETE = "_delete_"
_MISSING = object()

Schema = dict[str, dict[str, FieldSpec]]  # group name -> field name -> spec

# group name -> {removed field: one line on what it did, why it went and when}: a group's
# `REMOVED_FIELDS` class attribute, recorded by build_schema so that a config file or a command
# line naming a field that was taken out gets that line instead of "unknown field"
_REMOVED_NOTES: dict[str, dict[str, str]] = {}


class ConfigError(ValueError):
    """A configuration problem; the message names the file (or "command line") and the key."""

    def __init__(self, message: str, *, file: str | None = None, key: str | None = None):
        super().__init__(message)
        self.file = file
        self.key = key


def build_schema(groups: dict[str, type]) -> Schema:
    """Field specs of every group. Field names must be unique across groups, because 4DGS
    command lines (and 4DGS config files, which it flattens) address fields by bare name.

    Raises ValueError when two groups share a field name (a plugin programming error).
    """
    schema: Schema = {}
    owner: dict[str, str] = {}
    for name, cls in groups.items():
        specs = group_fields(cls, name)
        for fname in specs:
            if fname in owner:
                raise ValueError(f"parameter '{fname}' is defined by both {owner[fname]} and "
                                 f"{name}; field names must be unique across groups")
            owner[fname] = name
        schema[name] = specs
        _REMOVED_NOTES[name] = dict(getattr(cls, "REMOVED_FIELDS", None) or {})
    return schema


def removed_note(schema: Schema, name: str) -> str | None:
    """Why field ``name`` no longer exists in one of ``schema``'s groups (None when it never did)."""
    for group in schema:
        note = _REMOVED_NOTES.get(group, {}).get(name)
        if note:
            return f"{group}.{name} was removed {note}"
    return None


def field_owner(schema: Schema, name: str) -> str | None:
    """The group that defines field ``name``, or None."""
    for group, specs in schema.items():
        if name in specs:
            return group
    return None


def close_matches(word: str, candidates: list[str]) -> list[str]:
    return difflib.get_close_matches(word, candidates, n=3, cutoff=0.6)


@dataclass
class Layer:
    """Values one source contributes, with the source of each value."""

    values: dict[str, dict[str, Any]] = field(default_factory=dict)
    sources: dict[tuple[str, str], str] = field(default_factory=dict)

    def set(self, group: str, name: str, value: Any, source: str) -> None:
        self.values.setdefault(group, {})[name] = value
        self.sources[(group, name)] = source

    def get(self, group: str, name: str, default: Any = None) -> Any:
        return self.values.get(group, {}).get(name, default)


def merge_value(lower: Any, upper: Any) -> Any:
    """``upper`` over ``lower``: dicts merge recursively unless ``upper`` has ``_delete_``.

    ``_delete_`` markers are kept in the result (so a later merge onto the defaults still knows
    to replace); :func:`strip_markers` removes them at the end.
    """
    if isinstance(upper, dict) and isinstance(lower, dict) and not upper.get(DELETE, False):
        out = copy.deepcopy(lower)
        for key, value in upper.items():
            if key == DELETE:
                continue
            out[key] = merge_value(lower.get(key, _MISSING), value)
        return out
    return copy.deepcopy(upper)


def strip_markers(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: strip_markers(v) for k, v in value.items() if k != DELETE}
    if isinstance(value, list):
        return [strip_markers(v) for v in value]
    return value


def merge_layers(lower: Layer, upper: Layer) -> Layer:
    """A new layer with ``upper`` applied over ``lower``."""
    out = Layer(copy.deepcopy(lower.values), dict(lower.sources))
    for group, fields in upper.values.items():
        if fields.get(DELETE, False):
            out.values[group] = {DELETE: True}
            out.sources = {k: v for k, v in out.sources.items() if k[0] != group}
        target = out.values.setdefault(group, {})
        for name, value in fields.items():
            if name == DELETE:
                continue
            target[name] = merge_value(target.get(name, _MISSING), value)
            out.sources[(group, name)] = upper.sources[(group, name)]
    return out


def resolve(schema: Schema, classes: dict[str, type], layer: Layer
            ) -> tuple[dict[str, Any], dict[str, str]]:
    """Instances of every group in ``classes`` from defaults + ``layer``, after final checks.

    Returns ``(instances by group name, sources)`` where ``sources`` maps "Group.field" to where
    its value came from ("default", a file path, or "command line").
    Raises ConfigError (naming the source and key) when a field's check fails.
    """
    instances: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for group, cls in classes.items():
        kwargs: dict[str, Any] = {}
        for name, spec in schema[group].items():
            value = copy.deepcopy(spec.default)
            source = layer.sources.get((group, name), "default")
            given = layer.get(group, name, _MISSING)
            if given is not _MISSING:
                value = strip_markers(merge_value(value, given))
            if spec.check is not None:
                problem = spec.check(value)
                if problem:
                    raise ConfigError(f"{source}: {spec.qualname}: {problem}", file=source,
                                      key=spec.qualname)
            kwargs[name] = value
            sources[spec.qualname] = source
        instances[group] = cls(**kwargs)
    return instances, sources


def warn_compat_fields(schema: Schema, instances: dict[str, Any],
                       sources: dict[str, str]) -> list[str]:
    """Log one warning per compatibility-only field set to a non-default value.

    Returns the qualified names warned about (for callers and tests).
    """
    warned: list[str] = []
    for group, inst in instances.items():
        for name, spec in schema[group].items():
            value = getattr(inst, name)
            if spec.compat and value != spec.default:
                log.warning("%s = %r (from %s) has no effect in this implementation; it is "
                            "accepted for 4DGS compatibility only", spec.qualname, value,
                            sources[spec.qualname])
                warned.append(spec.qualname)
    return warned
