"""Differentiable Gaussian rasterizer with reference, cpu and gsplat backends.

See docs/ARCHITECTURE.md ("baselines/render") for the contract shared by every backend.
"""
from .api import RasterMeta, composite, project_gaussians, rasterize
from .backends import available_backends
from .projection import Projection
from .sh import RGB2SH, SH2RGB, eval_sh, sh_to_rgb

__all__ = [
    "rasterize", "project_gaussians", "composite", "RasterMeta", "Projection", "available_backends",
    "eval_sh", "sh_to_rgb", "RGB2SH", "SH2RGB",
]
