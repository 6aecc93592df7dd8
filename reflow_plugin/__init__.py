"""ReFlow (CVPR 2026) as a plugin of the 4DGS host: ``python train.py --plugin reflow``.

Modules: params (ReFlowParams), pairs (frame pairs), flow (full/camera flow maps), warp (warping,
photometric loss), matching (flow matching losses), separation (static/dynamic deformation),
labels / seeding (motion masks, labels, dynamic points), evaluate (flow EPE), visualize (flow
pictures), plugin (the hooks). The host finds the plugin through the entry point
``fourdgs.plugins: reflow = reflow_plugin.plugin:ReFlowPlugin`` (setup.cfg).
"""
from .params import ReFlowParams

__all__ = ["ReFlowParams"]
