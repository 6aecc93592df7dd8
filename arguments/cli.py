"""Command lines of train.py and render.py (4DGS's flags, plus ``--configs``/``--plugin``/...).

Every field of every parameter group is a flag named after it (``--iterations``, ``-s``/
``--source_path``, ...). Boolean fields take ``--name`` (True) and ``--no-name`` (False), so
4DGS's True defaults (``--white_background``, ``--eval``) can be switched off. List fields take
one or more tokens (``--test_iterations 3000 7000``) or one Python literal
(``--multires "[1, 2]"``); dict fields take a Python literal (``--kplanes_config
"{'resolution': [32, 32, 32, 12]}"``), which merges into the configured dict like a config file
does. Only flags actually typed override config files (see ``arguments/config.py`` for the
precedence rules).
"""
from __future__ import annotations

import argparse
import ast
import copy
import difflib
import json
import os
import sys
import typing
from dataclasses import dataclass, field
from typing import Any

from .config import load_configs, read_config_chain
from .fields import CoercionError, FieldSpec, coerce, split_comma_list
from .layers import ConfigError, Layer, Schema, build_schema, merge_layers, merge_value, removed_note, resolve, \
    strip_markers, warn_compat_fields
from .params import (HOST_GROUPS, ModelHiddenParams, ModelParams, OptimizationParams,
                     PipelineParams, RenderParams, RunParams)
from .saved import model_dir_of_checkpoint, read_saved_config, read_saved_model_config, read_saved_plugins

CLI = "command line"
_RESERVED = {*HOST_GROUPS, "RunParams", "RenderParams"}


@dataclass
class TrainArgs:
    """Everything train.py needs: the four 4DGS groups, plugin groups and run-level flags.

    ``sources`` maps "Group.field" to where its value came from ("default", a config file path,
    or "command line"); ``argv`` is the parsed command line.
    """

    model: ModelParams
    pipe: PipelineParams
    opt: OptimizationParams
    hidden: ModelHiddenParams
    run: RunParams
    extra: dict[str, Any] = field(default_factory=dict)
    sources: dict[str, str] = field(default_factory=dict)
    argv: list[str] = field(default_factory=list)

    def groups(self) -> dict[str, Any]:
        """All group instances by config-file group name (host groups, plugins, RunParams)."""
        return {"ModelParams": self.model, "PipelineParams": self.pipe,
                "OptimizationParams": self.opt, "ModelHiddenParams": self.hidden,
                **self.extra, "RunParams": self.run}


@dataclass
class RenderArgs:
    """What render.py needs: the training run's groups (restored from the model directory, then
    ``--configs``, then the command line) and the render flags."""

    model: ModelParams
    pipe: PipelineParams
    opt: OptimizationParams
    hidden: ModelHiddenParams
    run: RunParams  # the training run's flags (plugins, disabled components), as saved
    render: RenderParams
    extra: dict[str, Any] = field(default_factory=dict)
    sources: dict[str, str] = field(default_factory=dict)
    # model-shape fields (ModelHiddenParams, sh_degree) that --configs or flags typed here set to
    # another value than the trained run's, as "--name VALUE (trained: SAVED)"; named when the
    # saved files do not fit the model these values build
    shape_overrides: list[str] = field(default_factory=list)


def parse_train_args(argv: list[str] | None = None,
                     extra_groups: dict[str, type] | None = None,
                     saved_model_over_configs: bool = False) -> TrainArgs:
    """Parse train.py's command line and config files into typed groups.

    ``extra_groups`` maps a group name (as used in config files, e.g. "ReFlowParams") to a
    dataclass declared with :func:`arguments.fields.param`; its fields become flags too.
    Flag errors exit through argparse (status 2, with close matches for unknown flags); config
    problems raise :class:`ConfigError`.

    With ``--start_checkpoint`` naming an output folder and no ``--configs``, the model
    hyperparameters come from that folder's saved configuration (``config.json`` or 4DGS's
    ``cfg_args``), as ``render.py -m`` does; flags typed still win. ``saved_model_over_configs``:
    the ``--configs`` in ``argv`` were chosen for the user (train.py's family config), so that
    saved configuration goes over them (the family's schedule, the old run's model shapes).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = _check_extra(extra_groups)
    classes = {**HOST_GROUPS, **extra, "RunParams": RunParams}
    schema = build_schema(classes)
    parser = _build_parser(schema, classes, "Train a 4DGS model (optionally with plugins). The defaults "
                           "shown are 4DGS's; without --configs the dataset family's config file is "
                           "applied over them (named in the first log lines; e.g. the embedded scene "
                           "trains 300 + 2000 iterations), and typed flags override both. --configs none "
                           "keeps the defaults shown (the background excepted: see --white_background).")
    cli_layer = _parse_cli(parser, schema, argv)
    configs = cli_layer.get("RunParams", "configs", [])
    base = load_configs(configs, schema)
    old_run = model_dir_of_checkpoint(cli_layer.get("RunParams", "start_checkpoint"))
    if old_run is not None and (saved_model_over_configs or not configs):
        base = merge_layers(base, read_saved_model_config(old_run, schema))
    layer = merge_layers(base, cli_layer)
    instances, sources = resolve(schema, classes, layer)
    _absolute_source_path(instances["ModelParams"])
    warn_compat_fields(schema, instances, sources)
    return TrainArgs(model=instances["ModelParams"], pipe=instances["PipelineParams"],
                     opt=instances["OptimizationParams"], hidden=instances["ModelHiddenParams"],
                     run=instances["RunParams"], extra={k: instances[k] for k in extra},
                     sources=sources, argv=argv)


def parse_render_args(argv: list[str] | None = None,
                      extra_groups: dict[str, type] | None = None) -> RenderArgs:
    """Parse render.py's command line: ``-m MODEL`` (required), ``--iteration``,
    ``--skip_train/--skip_test/--skip_video``, ``--quiet``, ``--configs`` and the model,
    pipeline and hidden flags (``--backend``, ``--device``, ...).

    Values: defaults < the model directory's saved configuration (``config.json``, else 4DGS's
    ``cfg_args``) < ``--configs`` files < flags typed here (4DGS's get_combined_args, with
    the command line winning).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = _check_extra(extra_groups)
    cli_classes = {"ModelParams": ModelParams, "PipelineParams": PipelineParams,
                   "ModelHiddenParams": ModelHiddenParams, **extra, "RenderParams": RenderParams}
    run_classes = {**HOST_GROUPS, **extra, "RunParams": RunParams}
    cli_schema = build_schema(cli_classes)
    run_schema = build_schema(run_classes)
    parser = _build_parser(cli_schema, cli_classes, "Render a trained model's views. The defaults shown are "
                           "4DGS's; the model directory's saved configuration replaces them, then --configs "
                           "files, then the flags typed here.")
    cli_layer = _parse_cli(parser, cli_schema, argv)
    model_path = cli_layer.get("ModelParams", "model_path")
    if not model_path:
        parser.error("-m/--model_path (the trained model's directory) is required")
    saved = read_saved_config(model_path, run_schema)
    configs = cli_layer.get("RenderParams", "configs", [])
    layer = merge_layers(merge_layers(saved, load_configs(configs, run_schema)), cli_layer)
    instances, sources = resolve(run_schema, run_classes, layer)
    render, render_sources = resolve(cli_schema, {"RenderParams": RenderParams}, cli_layer)
    _absolute_source_path(instances["ModelParams"])
    warn_compat_fields(run_schema, instances, sources)
    return RenderArgs(model=instances["ModelParams"], pipe=instances["PipelineParams"],
                      opt=instances["OptimizationParams"],
                      hidden=instances["ModelHiddenParams"], run=instances["RunParams"],
                      render=render["RenderParams"], extra={k: instances[k] for k in extra},
                      sources={**sources, **render_sources},
                      shape_overrides=_shape_overrides(model_path, run_schema, instances))


def _shape_overrides(model_path: str, schema: Schema, instances: dict[str, Any]) -> list[str]:
    """Model-shape fields whose value for this render differs from the trained run's saved one."""
    saved = read_saved_model_config(model_path, schema)
    found = []
    for group, names in saved.values.items():
        for name, trained in names.items():
            value = getattr(instances[group], name)
            trained = strip_markers(merge_value(copy.deepcopy(schema[group][name].default), trained))
            if trained != value:
                found.append(f"{_flag_text(name, value)} (trained: {_value_text(trained)})")
    return found


def _flag_text(name: str, value: Any) -> str:
    """``--name value`` as typed on the command line (booleans as --name / --no-name)."""
    if isinstance(value, bool):
        return f"--{name}" if value else f"--no-{name}"
    return f"--{name} {_value_text(value)}"


def _value_text(value: Any) -> str:
    """A value as typed after its flag (lists space-separated, dicts as JSON; booleans as is)."""
    if isinstance(value, (list, tuple)):
        return " ".join(str(v) for v in value)
    if isinstance(value, dict):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


def peek_plugins(argv: list[str] | None = None, *, from_model_dir: bool = False) -> list[str]:
    """Plugin names requested by ``argv`` without parsing everything (plugins must be loaded
    first, because they contribute parameter groups and flags).

    Same precedence as the full parse: ``--plugin`` flags if any, else the last
    ``RunParams.plugin`` among the ``--configs`` files (with their bases), else (only with
    ``from_model_dir=True``, for render.py) the plugins saved in ``-m``'s configuration.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    # the same arity as the full parser's list flags (`--plugin a b` names two plugins)
    p.add_argument("--plugin", nargs="+", action="extend", default=[])
    p.add_argument("--configs", nargs="+", action="extend", default=[])
    p.add_argument("-m", "--model_path", default="")
    ns, _ = p.parse_known_args(argv)
    if ns.plugin:
        return split_comma_list(ns.plugin)
    plugins: list[str] = []
    if from_model_dir and ns.model_path:
        plugins = read_saved_plugins(ns.model_path)
    for config in ns.configs:
        for path, raw in read_config_chain(config):
            run = raw.get("RunParams")
            if isinstance(run, dict) and "plugin" in run:
                value = run["plugin"]
                tokens = [value] if isinstance(value, str) else value
                if not isinstance(tokens, (list, tuple)) or not all(isinstance(t, str)
                                                                    for t in tokens):
                    raise ConfigError(f"{path}: RunParams.plugin: expected a list of names, "
                                      f"got {value!r}", file=str(path), key="RunParams.plugin")
                plugins = split_comma_list(list(tokens))
    return plugins


# --------------------------------------------------------------------------------------------
# parser construction

def _check_extra(extra_groups: dict[str, type] | None) -> dict[str, type]:
    extra = dict(extra_groups or {})
    clash = sorted(set(extra) & _RESERVED)
    if clash:
        raise ValueError(f"plugin group name(s) {clash} clash with the host's groups")
    return extra


def _build_parser(schema: Schema, classes: dict[str, type],
                  description: str) -> argparse.ArgumentParser:
    # the full usage line lists ~90 flags; keep error messages readable
    parser = argparse.ArgumentParser(description=description, allow_abbrev=False,
                                     usage="%(prog)s [-h] [--configs FILE ...] [FLAG ...]")
    for group, specs in schema.items():
        cls = classes[group]
        doc = (cls.__doc__ or "").strip().splitlines()
        # dataclasses without a docstring get their signature as __doc__: not a description
        title = doc[0] if doc and not doc[0].startswith(cls.__name__ + "(") else None
        section = parser.add_argument_group(group, title)
        for spec in specs.values():
            _add_flag(section, spec)
    return parser


def _add_flag(group: argparse._ArgumentGroup, spec: FieldSpec) -> None:
    names = [f"--{spec.name}"] + ([f"-{spec.short}"] if spec.short else [])
    notes = []
    if spec.compat:
        notes.append("4DGS compatibility only, no effect")
    if spec.ours:
        notes.append("not in 4DGS")
    help_text = spec.help + (f" ({'; '.join(notes)})" if notes else "")
    help_text = f"{help_text} [default: {spec.default!r}]".replace("%", "%%")
    common = dict(dest=spec.qualname, default=argparse.SUPPRESS, help=help_text)
    kind = spec.kind
    if kind == "bool":
        group.add_argument(*names, action=argparse.BooleanOptionalAction, **common)
    elif kind == "list":
        # comma lists and --configs accumulate over repeated flags; other lists are replaced
        extend = spec.comma_list or spec.name == "configs"
        group.add_argument(*names, nargs="+", action="extend" if extend else "store",
                           metavar=spec.name.upper(), **common)
    elif kind == "dict":
        group.add_argument(*names, metavar="DICT_LITERAL", **common)
    else:
        choices = list(spec.choices) if spec.choices else None
        group.add_argument(*names, metavar=spec.name.upper() if not choices else None,
                           choices=choices, **common)


# --------------------------------------------------------------------------------------------
# parsing

def _parse_cli(parser: argparse.ArgumentParser, schema: Schema, argv: list[str]) -> Layer:
    ns, unknown = parser.parse_known_args(argv)
    if unknown:
        parser.error(_unknown_message(parser, unknown, schema))
    layer = Layer()
    for dest, raw in vars(ns).items():
        group, name = dest.split(".", 1)
        spec = schema[group][name]
        try:
            value = coerce(spec, _from_cli(spec, raw))
        except (CoercionError, ValueError, SyntaxError) as err:
            parser.error(f"argument --{name}: {err}")
        problem = spec.check(value) if spec.check and spec.kind != "dict" else None
        if problem:
            parser.error(f"argument --{name}: {problem}")
        layer.set(group, name, value, CLI)
    return layer


def _unknown_message(parser: argparse.ArgumentParser, unknown: list[str], schema: Schema) -> str:
    options = list(parser._option_string_actions)  # every registered flag, --no-* included
    parts = []
    for token in unknown:
        flag = token.split("=", 1)[0].lstrip("-")
        note = removed_note(schema, flag[3:] if flag.startswith("no-") else flag) if token.startswith("--") else None
        if note:
            return f"argument {token.split('=', 1)[0]}: {note}"
        if token.startswith("-"):
            close = difflib.get_close_matches(token.split("=", 1)[0], options, n=3, cutoff=0.6)
            parts.append(token + (f" (did you mean {', '.join(close)}?)" if close else ""))
        else:
            parts.append(token)
    return "unrecognized arguments: " + " ".join(parts)


def _from_cli(spec: FieldSpec, raw: Any) -> Any:
    """Turn argparse's strings into Python values (coerce() then checks the type)."""
    kind = spec.kind
    if kind == "bool":
        return raw
    if kind == "dict":
        return ast.literal_eval(raw)
    if kind == "list":
        tokens: list[str] = raw
        if len(tokens) == 1 and tokens[0].lstrip()[:1] in ("[", "("):
            return ast.literal_eval(tokens[0])  # --multires "[1, 2]"
        item_type = typing.get_args(spec.base_type)[0]
        if item_type is str:
            return tokens
        return [_literal(t, item_type) for t in tokens]
    if spec.base_type is str:
        return raw
    return _literal(raw, spec.base_type)


def _literal(token: str, expected: type) -> Any:
    try:
        return ast.literal_eval(token)
    except (ValueError, SyntaxError):
        raise CoercionError(f"expected {expected.__name__}, got {token!r}") from None


def _absolute_source_path(model: ModelParams) -> None:
    # as 4DGS's ModelParams.extract; empty stays empty (= the embedded synthetic scene)
    if model.source_path:
        model.source_path = os.path.abspath(os.path.expanduser(model.source_path))
