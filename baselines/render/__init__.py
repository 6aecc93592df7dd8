"""Differentiable Gaussian rasterizer with reference, cpu and gsplat backends.

See docs/ARCHITECTURE.md ("baselines/render") for the contract shared by every backend.
"""
from .api import RasterMeta, composite, project_gaussians, rasterize
from .backends import available_backends
from .projection import Projection

__all__ = ["rasterize", "project_gaussians", "composite", "RasterMeta", "Projection", "available_backends"]
