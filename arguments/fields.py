"""Field declarations for parameter groups: metadata, type introspection and value coercion.

A parameter group is a plain dataclass whose fields are declared with :func:`param`, which stores
in the field metadata everything the config loader and the command line need:

- ``help``: one line shown by ``--help``;
- ``compat``: True for fields that exist only so that 4DGS config files and command lines keep
  working; they have no effect in this implementation (a non-default value logs one warning);
- ``ours``: True for fields this project adds on top of 4DGS's;
- ``short``: a one-letter alias (4DGS's ``-s``, ``-m``, ``-i``, ``-r``, ``-w``);
- ``choices``: allowed values; ``check``: a callable returning an error message or None;
- ``comma_list``: for ``list[str]`` fields, command-line tokens and config strings are split on
  commas (``--plugin a,b --plugin c``).

Supported field types: ``bool``, ``int``, ``float``, ``str``, ``X | None`` of those,
``list[X]`` of scalars and ``dict[str, Any]``. Plugin groups use the same helper.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

_SCALARS = (bool, int, float, str)


def param(default: Any, help: str, *, compat: bool = False, ours: bool = False,
          short: str | None = None, choices: tuple[Any, ...] | None = None,
          check: Callable[[Any], str | None] | None = None,
          comma_list: bool = False) -> Any:
    """Declare a parameter-group field (returns a ``dataclasses.field``).

    Mutable defaults (lists, dicts) are deep-copied per instance.
    """
    metadata = {"help": help, "compat": compat, "ours": ours, "short": short,
                "choices": choices, "check": check, "comma_list": comma_list}
    if isinstance(default, (list, dict)):
        frozen = copy.deepcopy(default)
        return dataclasses.field(default_factory=lambda: copy.deepcopy(frozen), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


@dataclass(frozen=True)
class FieldSpec:
    """Everything known about one field of a parameter group."""

    group: str
    name: str
    type: Any  # the resolved annotation
    default: Any
    help: str
    compat: bool
    ours: bool
    short: str | None
    choices: tuple[Any, ...] | None
    check: Callable[[Any], str | None] | None
    comma_list: bool

    @property
    def qualname(self) -> str:
        return f"{self.group}.{self.name}"

    @property
    def base_type(self) -> Any:
        """The annotation without ``| None``."""
        return _strip_optional(self.type)[0]

    @property
    def optional(self) -> bool:
        return _strip_optional(self.type)[1]

    @property
    def kind(self) -> str:
        """One of 'bool', 'int', 'float', 'str', 'list', 'dict'."""
        origin = typing.get_origin(self.base_type) or self.base_type
        if origin in (list, tuple):
            return "list"
        if origin is dict:
            return "dict"
        return self.base_type.__name__


def _strip_optional(tp: Any) -> tuple[Any, bool]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) != 1:
            raise TypeError(f"unsupported union annotation {tp!r}")
        return args[0], True
    return tp, False


def group_fields(cls: type, group_name: str | None = None) -> dict[str, FieldSpec]:
    """Field specs of a parameter-group dataclass, in declaration order.

    Raises TypeError for a class that is not a dataclass or has an unsupported annotation
    (a programming error in the group's definition, so it surfaces at parser construction).
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"parameter group {cls!r} is not a dataclass")
    name = group_name or cls.__name__
    hints = typing.get_type_hints(cls)
    specs: dict[str, FieldSpec] = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            raise TypeError(f"{name}.{f.name} has no default; every parameter needs one")
        md = f.metadata
        spec = FieldSpec(group=name, name=f.name, type=hints[f.name], default=default,
                         help=md.get("help", ""), compat=md.get("compat", False),
                         ours=md.get("ours", False), short=md.get("short"),
                         choices=md.get("choices"), check=md.get("check"),
                         comma_list=md.get("comma_list", False))
        _validate_annotation(spec)
        specs[f.name] = spec
    return specs


def _validate_annotation(spec: FieldSpec) -> None:
    base = spec.base_type
    origin = typing.get_origin(base)
    if base in _SCALARS:
        return
    if origin in (list, tuple):
        args = typing.get_args(base)
        if len(args) == 1 and args[0] in _SCALARS:
            return
    if origin is dict:
        return
    raise TypeError(f"{spec.qualname}: unsupported annotation {spec.type!r} "
                    "(use bool, int, float, str, X | None, list[scalar] or dict[str, Any])")


class CoercionError(ValueError):
    """A value does not fit a field's type; the message says what was expected."""


def coerce(spec: FieldSpec, value: Any) -> Any:
    """Return ``value`` converted to the field's type where lossless, else raise CoercionError.

    Lossless conversions: int -> float, integral float -> int, tuple -> list, and (for
    ``comma_list`` fields) a comma-separated string -> list of names. bool is never taken for a
    number and numbers are never taken for bool; a float field takes finite numbers only.
    """
    if value is None:
        if spec.optional:
            return None
        raise CoercionError(f"expected {_type_name(spec)}, got None")
    kind = spec.kind
    if kind == "list":
        return _coerce_list(spec, value)
    if kind == "dict":
        if not isinstance(value, dict):
            raise CoercionError(f"expected a dict, got {type(value).__name__} {value!r}")
        return copy.deepcopy(value)
    out = _coerce_scalar(spec.base_type, value, _type_name(spec))
    if spec.choices is not None and out not in spec.choices:
        raise CoercionError(f"expected one of {list(spec.choices)}, got {out!r}")
    return out


def _coerce_scalar(tp: type, value: Any, expected: str) -> Any:
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                out = float(value)
            except OverflowError:  # an int beyond float range
                out = math.inf
            if not math.isfinite(out):  # 1e999 on a command line, float('nan') in a config file
                raise CoercionError(f"expected a finite number, got {out!r}")
            return out
    elif tp is str:
        if isinstance(value, str):
            return value
    raise CoercionError(f"expected {expected}, got {type(value).__name__} {value!r}")


def _coerce_list(spec: FieldSpec, value: Any) -> list[Any]:
    item_type = typing.get_args(spec.base_type)[0]
    if spec.comma_list and isinstance(value, str):
        value = split_comma_list([value])
    if not isinstance(value, (list, tuple)):
        raise CoercionError(f"expected {_type_name(spec)}, got {type(value).__name__} {value!r}")
    items = [_coerce_scalar(item_type, v, f"{item_type.__name__} items") for v in value]
    if spec.comma_list:
        items = split_comma_list(items)
    if spec.choices is not None:
        bad = [v for v in items if v not in spec.choices]
        if bad:
            raise CoercionError(f"items must be in {list(spec.choices)}, got {bad}")
    return items


def as_dict(instance: Any) -> dict[str, Any]:
    """A parameter-group instance as a plain dict (declaration order, values deep-copied)."""
    return {f.name: copy.deepcopy(getattr(instance, f.name))
            for f in dataclasses.fields(instance)}


def split_comma_list(tokens: list[str]) -> list[str]:
    """Split tokens on commas, strip blanks, drop empties and repeats (order kept)."""
    out: list[str] = []
    for token in tokens:
        for part in token.split(","):
            part = part.strip()
            if part and part not in out:
                out.append(part)
    return out


def _type_name(spec: FieldSpec) -> str:
    kind = spec.kind
    if kind == "list":
        name = f"list of {typing.get_args(spec.base_type)[0].__name__}"
        if spec.comma_list:
            name += " (or a comma-separated string)"
    elif kind == "dict":
        name = "a dict"
    else:
        name = kind
    return name + (" or None" if spec.optional else "")
