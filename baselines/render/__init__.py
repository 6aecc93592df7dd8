"""Differentiable Gaussian rasterizer with reference, cpu and gsplat backends."""
