"""Rendering of the (deformed) Gaussian model into one camera, in two steps.

`prepare_view` deforms the Gaussians to the camera's time, computes their view-dependent colours
and projects them (`prepare_views`: several cameras, ONE deformation call); `composite_view`
rasterizes colours plus any extra per-Gaussian channels in ONE pass. The split lets the trainer
prepare every view of a batch first, so a plugin can build a view's extra channels from another
view's projection (flow between a frame pair) at no extra rasterization cost. `render` does both
for evaluation.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from baselines.render import composite, project_gaussians
from baselines.render.sh import sh_to_rgb

from .hooks import ViewRender

if TYPE_CHECKING:
    from baselines.data import Camera

    from .gaussian_model import GaussianModel
    from .state import GaussianState


def prepare_view(model: GaussianModel, camera: Camera, stage: str, backend: str = "auto",
                 colors: bool = True, state: GaussianState | None = None) -> ViewRender:
    """Deform to camera.time, evaluate SH colours and project (no compositing yet).

    Args:
        colors: False for a view that is only projected, never composited (a plugin's partner
            frame): its `colors` stay None.
        state: the Gaussians already deformed to camera.time (`prepare_views`), else deformed here.
    Returns:
        ViewRender with state, colors [N, 3] and projection filled in; means2d retains its grad
        (densification statistics read it after backward).
    """
    if state is None:
        state = model.deform(camera.time, stage)
    rgb = sh_to_rgb(state.shs, state.means, camera.camera_center, model.active_sh_degree) if colors else None
    projection = project_gaussians(
        state.means, state.quats, state.scales, camera.viewmat, camera.K, camera.width, camera.height,
        opacities=state.opacities, backend=backend,
    )
    if projection.means2d.requires_grad:
        projection.means2d.retain_grad()
    return ViewRender(camera=camera, state=state, colors=rgb, projection=projection)


def prepare_views(model: GaussianModel, cameras: Sequence[Camera], stage: str, backend: str = "auto",
                  colors: Sequence[bool] | None = None, rows: Sequence[Tensor | None] | None = None,
                  shared: Sequence[tuple[int, Tensor] | None] | None = None) -> list[ViewRender]:
    """`prepare_view` of every camera, the deformation to all their times in one call
    (`GaussianModel.deform_many`); `colors[k]` as prepare_view's `colors` (default all True);
    `rows[k]` ([N] bool or None) as deform_many's `rows` (the Gaussians read at camera k's time);
    `shared[k]` ((j, [N] bool) or None) as deform_many's `shared` (rows taken from camera j's time)."""
    colors = [True] * len(cameras) if colors is None else list(colors)
    if len(colors) != len(cameras):
        raise ValueError(f"prepare_views: {len(colors)} colour flags for {len(cameras)} cameras")
    states = model.deform_many([camera.time for camera in cameras], stage, rows, shared)
    return [prepare_view(model, camera, stage, backend, flag, state)
            for camera, flag, state in zip(cameras, colors, states)]


def composite_view(
    view: ViewRender, background: Tensor, extra_features: dict[str, Tensor] | None = None, backend: str = "auto"
) -> ViewRender:
    """Rasterize colours and extra channels of a prepared view in one pass (fills image/depth/alpha/extras).

    Args:
        view: from prepare_view. background: [3] RGB background (extra channels get 0).
        extra_features: {name: [N, c]} per-Gaussian channels; their maps land in view.extras.
    """
    extra_features = extra_features or {}
    n = view.colors.shape[0]
    blocks, names, widths = [view.colors], [], []
    for name, feats in extra_features.items():
        if feats.dim() != 2 or feats.shape[0] != n:
            raise ValueError(f"extra feature {name!r} must have shape [N, c] with N={n}, got {tuple(feats.shape)}")
        blocks.append(feats.to(view.colors.dtype))
        names.append(name)
        widths.append(feats.shape[1])
    features = torch.cat(blocks, dim=1) if len(blocks) > 1 else view.colors
    bg = torch.cat([background, background.new_zeros(sum(widths))]) if widths else background
    cam = view.camera
    try:
        image, depth, alpha = composite(
            view.projection, view.state.opacities, features, cam.width, cam.height, backend=backend, background=bg
        )
    except ValueError as error:
        raise _name_bad_channels(error, cam.image_name, [view.colors, *blocks[1:]], ["colours", *names]) from error
    view.image, view.depth, view.alpha = image[..., :3], depth, alpha
    start = 3
    view.extras = {}
    for name, width in zip(names, widths):
        view.extras[name] = image[..., start : start + width]
        start += width
    return view


def _name_bad_channels(error: ValueError, image_name: str, blocks: list[Tensor], names: list[str]) -> ValueError:
    """The rasterizer's "features contains NaN or inf", with the block (colours or a plugin's channel)
    and the number of Gaussians named; other errors unchanged. Only runs when compositing failed."""
    bad = [(name, int((~torch.isfinite(block)).any(dim=1).sum())) for name, block in zip(names, blocks)]
    bad = [(name, count) for name, count in bad if count]
    if not bad:
        return error
    what = ", ".join(f"{name!r} in {count} Gaussian(s)" for name, count in bad)
    return ValueError(f"non-finite per-Gaussian channels while rendering view {image_name}: {what} "
                      f"(of {blocks[0].shape[0]}); the channels' producer (the host for colours, else the plugin "
                      f"that adds them) computed them from this iteration's Gaussians")


def render(
    model: GaussianModel, camera: Camera, stage: str, background: Tensor, backend: str = "auto"
) -> ViewRender:
    """Deform, project and composite one view (no plugin channels)."""
    return composite_view(prepare_view(model, camera, stage, backend), background, None, backend)
