"""ReFlow's render modes in the web viewer (view.py): the rendered full flow, as a colour wheel.

    modes = ReFlowPlugin(...).viewer_modes()        # {"full flow": full_flow_mode}

The full flow of the viewer's camera from t to t + dt (one video frame; t - dt at the end of
the time span), with the camera held still: the image motion of the scene itself, rendered
exactly as training renders it (one pass of `flow_features` channels, DESIGN.md section 5).
Colours are the Middlebury wheel (white = still); a picture saturates at the viewer's colour
scale (px) when one is set, else at its own 99th percentile speed; the caption gives it. Pixels
with alpha < 0.5 are black.
"""
from __future__ import annotations

import numpy as np
import torch

from baselines.render import composite, project_gaussians
from baselines.viewer.frame import ViewFrame

from .flow import flow_features, full_flow
from .visualize import flow_to_color

MIN_ALPHA = 0.5
MIN_SCALE = 0.05  # px: a still scene stays white instead of amplifying rounding noise


@torch.no_grad()
def full_flow_mode(frame: ViewFrame) -> tuple[np.ndarray, str]:
    """[H, W, 3] uint8 flow picture of the frame's camera from t to t +- dt, and its caption."""
    forward = frame.time + frame.dt <= 1.0 + 1e-6
    target = frame.time + frame.dt if forward else frame.time - frame.dt
    a, b = frame.state, frame.deform(target)
    projections = [project_gaussians(s.means, s.quats, s.scales, frame.viewmat, frame.K, frame.width, frame.height,
                                     opacities=s.opacities, backend=frame.backend) for s in (a, b)]
    maps, _, alpha = composite(projections[0], a.opacities, flow_features(*projections), frame.width, frame.height,
                               backend=frame.backend)
    flow, valid = full_flow(maps, alpha, MIN_ALPHA)
    flow_np, valid_np = flow.cpu().numpy(), valid.cpu().numpy()
    speeds = np.linalg.norm(flow_np[valid_np], axis=-1)
    own = max(float(np.percentile(speeds, 99)) if speeds.size else 0.0, MIN_SCALE)
    scale = frame.color_scale if frame.color_scale > 0 else own
    arrow = "t+dt" if forward else "t-dt"
    fastest = float(speeds.max()) if speeds.size else 0.0
    return (flow_to_color(flow_np, scale, valid_np),
            f"flow t->{arrow}: full colour = {scale:.2f} px (fastest {fastest:.2f} px)")


VIEWER_MODES = {"full flow": full_flow_mode}
