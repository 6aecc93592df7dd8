"""Typed parameter groups (4DGS names and defaults), 4DGS-style config files, command lines.

    from arguments import parse_train_args, peek_plugins, write_cfg_args
    args = parse_train_args(extra_groups=plugin_groups)   # TrainArgs: model, pipe, opt, hidden, run, extra

Precedence: dataclass defaults < config files (``--configs`` order, each after its ``_base_``
chain) < flags typed on the command line. See ``arguments/config.py`` for the file format.
"""
from .cli import RenderArgs, TrainArgs, parse_render_args, parse_train_args, peek_plugins
from .config import load_config, load_configs, read_config_chain
from .fields import FieldSpec, as_dict, group_fields, param
from .layers import ConfigError
from .params import (HOST_GROUPS, ModelHiddenParams, ModelParams, OptimizationParams,
                     PipelineParams, RenderParams, RunParams)
from .saved import read_saved_config, write_cfg_args

__all__ = [
    "ConfigError", "FieldSpec", "HOST_GROUPS", "ModelHiddenParams", "ModelParams",
    "OptimizationParams", "PipelineParams", "RenderArgs", "RenderParams", "RunParams",
    "TrainArgs", "as_dict", "group_fields", "load_config", "load_configs", "param",
    "parse_render_args", "parse_train_args", "peek_plugins", "read_config_chain",
    "read_saved_config", "write_cfg_args",
]
