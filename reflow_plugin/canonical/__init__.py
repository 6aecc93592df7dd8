"""Complete canonical space (ReFlow paper 3.2.1, appendix A.1; issue 9).

    space = build_canonical_space(scene, masks, options_from_params(params), cache_dir, progress=True)
    space.static, space.dynamic        # PointCloud (static: fused, voxelised; dynamic: reference frame)
    space.reference_frame              # index into scene.train_cameras (None without masks)
    space.report                       # JSON-able: provider, frames, edges, residuals, timings, cache
    space.write_ply(run_dir)           # static.ply, dynamic.ply (atomic)

Modules: providers (pairwise pointmaps), alignment (global alignment of one pair graph),
coarse_to_fine (keyframes then clips), split (static/dynamic clouds), cache.
"""
from __future__ import annotations

from .space import CanonicalOptions, CanonicalSpace, build_canonical_space, make_provider, options_from_params

__all__ = ["CanonicalOptions", "CanonicalSpace", "build_canonical_space", "make_provider", "options_from_params"]
