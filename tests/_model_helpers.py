"""Shared builders for the tests of baselines/fourdgs (model, hexplane, checkpoint, densification)."""

from __future__ import annotations

import types

import numpy as np
import torch

from baselines.fourdgs.deformation import HIDDEN_DEFAULTS
from baselines.fourdgs.gaussian_model import GaussianModel

# 4DGS OptimizationParams defaults (arguments/__init__.py).
OPT_DEFAULTS = dict(
    iterations=30_000, coarse_iterations=3000,
    position_lr_init=0.00016, position_lr_final=0.0000016, position_lr_delay_mult=0.01, position_lr_max_steps=20_000,
    deformation_lr_init=0.00016, deformation_lr_final=0.000016, deformation_lr_delay_mult=0.01,
    grid_lr_init=0.0016, grid_lr_final=0.00016,
    feature_lr=0.0025, opacity_lr=0.05, scaling_lr=0.005, rotation_lr=0.001, percent_dense=0.01,
    opacity_reset_interval=3000, densification_interval=100, densify_from_iter=500, densify_until_iter=15_000,
    densify_grad_threshold_coarse=0.0002, densify_grad_threshold_fine_init=0.0002,
    densify_grad_threshold_after=0.0002, pruning_from_iter=500, pruning_interval=100,
    opacity_threshold_coarse=0.005, opacity_threshold_fine_init=0.005, opacity_threshold_fine_after=0.005,
)

SMALL_PLANES = {"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 4, "resolution": [6, 5, 7, 4]}


def opt_args(**overrides) -> types.SimpleNamespace:
    return types.SimpleNamespace(**{**OPT_DEFAULTS, **overrides})


def hidden_args(**overrides) -> types.SimpleNamespace:
    """4DGS ModelHiddenParams defaults, small planes unless overridden."""
    values = {**HIDDEN_DEFAULTS, "kplanes_config": dict(SMALL_PLANES), "multires": [1, 2], "net_width": 16,
              "defor_depth": 1, **overrides}
    return types.SimpleNamespace(**values)


def make_model(count: int = 40, seed: int = 0, sh_degree: int = 3, setup: bool = True, **hidden) -> GaussianModel:
    """A model from a random coloured cloud, optionally with its optimizer built."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = GaussianModel(sh_degree, hidden_args(**hidden))
    model.create_from_pcd(rng.uniform(-1, 1, (count, 3)), rng.uniform(0, 1, (count, 3)), spatial_lr_scale=2.0)
    if setup:
        model.training_setup(opt_args())
    return model
