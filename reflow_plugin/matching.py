"""Self-correction flow matching losses of one frame pair (paper section 3.3, DESIGN.md section 5).

For each direction (a -> b and b -> a) of the pair:

    full flow F   (from view a's flow channels)        camera flow F^cam (from view a's depth)
    L_mc   = photo(I_b warped by F, I_a)               L^cam_mc = photo(I_b warped by F^cam, I_a)   on static pixels
    L_cr   = photo(render_b warped by F, I_a)          L^cam_cr = photo(render_b warped by F^cam, I_a) on static pixels

on the pixels where the flow is valid and lands inside image b (and, with the `occlusion`
component, passes the forward-backward test of the pair's two full flows; with `cam_occlusion`,
the camera-flow terms pass the same test on the pair's two camera flows; with
`full_flow_dynamic_only`, a diagnostic of ours, L_mc and L_cr only on dynamic pixels, each pixel
weighted as in the loss over all pixels). Static pixels: the
rendered dynamic-ness channel (1 for dynamic Gaussians) below 0.5 of the pixel's opacity; with
`moving` masks (the coarse stage, where the dynamic Gaussians are hidden and that channel is 0
everywhere) also outside view a's mask, and sampling view b outside its mask.
Directions are averaged; the returned terms are already weighted:

    ff_mc = lambda_ff * lambda_mc * L_mc        ff_cr = lambda_ff * lambda_cr * L_cr
    cf_mc = lambda_cf * lambda_mc * L^cam_mc    cf_cr = lambda_cf * lambda_cr * L^cam_cr

with lambda_cr = cross_time_ratio * lambda_mc (paper: 0.1). `blur_sigmas` (ours, off by default)
adds motion-consistency terms on blurred images, averaged with the full-resolution one: a
photometric loss only "sees" motion within about a pixel of its sample, blur widens that range.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from torch import Tensor

from baselines.fourdgs.hooks import ViewRender

from .flow import camera_flow, full_flow
from .warp import backward_warp, occlusion_mask, photometric_losses

FLOW_KEY = "reflow_flow"
DYNAMIC_KEY = "reflow_dynamic"
STATIC_BELOW = 0.5


@dataclass
class MatchingConfig:
    """Weights and options of the flow matching losses (from ReFlowParams)."""

    lambda_ff: float = 5.0
    lambda_cf: float = 0.3
    lambda_mc: float = 1.0
    cross_time_ratio: float = 0.1
    ssim_weight: float = 0.2
    min_alpha: float = 0.5
    blur_sigmas: tuple[float, ...] = ()
    occlusion: bool = False
    occlusion_alpha1: float = 0.01
    occlusion_alpha2: float = 0.5
    full_flow_dynamic_only: bool = False  # full flow terms on dynamic pixels only (needs extras[DYNAMIC_KEY])
    cam_occlusion: bool = False  # forward-backward test on the two camera flows

    @property
    def lambda_cr(self) -> float:
        return self.cross_time_ratio * self.lambda_mc


@dataclass
class Direction:
    """What one direction a -> b computed (kept for diagnostics and the flow panels)."""

    flow: Tensor | None = None  # [H, W, 2] full flow
    valid: Tensor | None = None  # [H, W] bool: where L_mc was evaluated
    warped: Tensor | None = None  # [H, W, 3] I_b warped to a
    cam_flow: Tensor | None = None
    static: Tensor | None = None  # [H, W] bool: where L^cam_mc was evaluated


@dataclass
class PairResult:
    losses: dict[str, Tensor] = field(default_factory=dict)
    directions: list[Direction] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)


class _Terms:
    """Photometric terms collected over both directions, evaluated in one batched call."""

    def __init__(self) -> None:
        self.names: list[str] = []
        self.preds: list[Tensor] = []
        self.targets: list[Tensor] = []
        self.masks: list[Tensor] = []
        self.weights: list[Tensor | float] = []

    def add(self, name: str, pred: Tensor, target: Tensor, mask: Tensor, weight: Tensor | float = 1.0) -> None:
        """One term: the masked photometric loss of pred vs target, times `weight`."""
        self.names.append(name)
        self.preds.append(pred)
        self.targets.append(target)
        self.masks.append(mask)
        self.weights.append(weight)

    def means(self, ssim_weight: float) -> dict[str, Tensor]:
        """{name: mean of its terms}."""
        values = photometric_losses(torch.stack(self.preds), torch.stack(self.targets), torch.stack(self.masks),
                                    ssim_weight)
        values = values * torch.stack([torch.as_tensor(w, dtype=values.dtype, device=values.device)
                                       for w in self.weights])
        out: dict[str, Tensor] = {}
        for name in dict.fromkeys(self.names):
            out[name] = values[[i for i, n in enumerate(self.names) if n == name]].mean()
        return out


def _static_pixels(view: ViewRender) -> Tensor:
    """[H, W] bool: pixels whose rendered dynamic share (extras[DYNAMIC_KEY] / alpha) is below STATIC_BELOW."""
    return (view.extras[DYNAMIC_KEY][..., 0] / view.alpha[..., 0].clamp_min(1e-6)) < STATIC_BELOW


def _off_moving(moving: Sequence[Tensor], k: int, flow: Tensor) -> Tensor:
    """[H, W] bool: view k's pixel lies outside its motion mask and its sample in the other view
    (at q + flow, bilinear: all four neighbours) outside that view's mask."""
    lands, _ = backward_warp(moving[1 - k].to(flow.dtype).unsqueeze(-1), flow)
    return ~moving[k] & (lands[..., 0] < 1e-6)


def pair_losses(views: list[ViewRender], config: MatchingConfig, use_full: bool, use_cam: bool,
                blurred: Callable[[int, float], tuple[Tensor, Tensor]] | None = None,
                moving: Sequence[Tensor] | None = None) -> PairResult:
    """Flow matching losses of a 2-view batch (see the module docstring).

    Args:
        views: the pair's two composited views; with `use_full` each carries extras[FLOW_KEY]
            ([H, W, 7] flow channels towards the other view), with `use_cam` or
            `config.full_flow_dynamic_only` extras[DYNAMIC_KEY] ([H, W, 1]).
        blurred: (view index k, sigma) -> (blurred I_other, blurred I_k), for `blur_sigmas`.
        moving: per view [H, W] bool motion masks (True = moving) kept out of camera-flow matching.
    """
    result = PairResult()
    terms = _Terms()
    full_flows = []
    if use_full:
        for k in range(2):
            full_flows.append(full_flow(views[k].extras[FLOW_KEY], views[k].alpha, config.min_alpha))
    camera_flows = []
    if use_cam:
        for k in range(2):
            a, b = views[k], views[1 - k]
            camera_flows.append(camera_flow(a.depth, a.alpha, a.camera.K, a.camera.viewmat, b.camera.K,
                                            b.camera.viewmat, config.min_alpha))
    for k in range(2):
        a, b = views[k], views[1 - k]
        gt_a = a.camera.image
        sources = torch.cat((b.camera.image, b.image), dim=-1)  # warp ground truth and render together
        direction = Direction()
        if use_full:
            flow, valid = full_flows[k]
            warped, inside = backward_warp(sources, flow)
            mask = valid & inside
            if config.occlusion:
                mask = mask & occlusion_mask(flow, full_flows[1 - k][0], config.occlusion_alpha1, config.occlusion_alpha2)
            weight: Tensor | float = 1.0
            if config.full_flow_dynamic_only:
                # same per-pixel weight as over all pixels: the mean over the dynamic pixels times their share
                dynamic = mask & ~_static_pixels(a)
                weight = dynamic.sum().float() / mask.sum().clamp_min(1).float()
                mask = dynamic
            terms.add("mc", warped[..., :3], gt_a, mask, weight)
            terms.add("cr", warped[..., 3:], gt_a, mask, weight)
            if blurred is not None:
                for sigma in config.blur_sigmas:
                    blur_b, blur_a = blurred(k, sigma)
                    terms.add("mc", backward_warp(blur_b, flow)[0], blur_a, mask, weight)
            direction.flow, direction.valid, direction.warped = flow, mask, warped[..., :3]
            result.metrics[f"flow_valid_{k}"] = float(mask.float().mean())
        if use_cam:
            flow_c, valid_c = camera_flows[k]
            static = _static_pixels(a)
            if moving is not None:
                static = static & _off_moving(moving, k, flow_c)
            warped_c, inside = backward_warp(sources, flow_c)
            mask = valid_c & inside & static
            if config.cam_occlusion:
                mask = mask & occlusion_mask(flow_c, camera_flows[1 - k][0], config.occlusion_alpha1,
                                             config.occlusion_alpha2)
            terms.add("cam_mc", warped_c[..., :3], gt_a, mask)
            terms.add("cam_cr", warped_c[..., 3:], gt_a, mask)
            direction.cam_flow, direction.static = flow_c, mask
        result.directions.append(direction)
    if not terms.names:
        return result
    means = terms.means(config.ssim_weight)
    if use_full:
        # blurred terms share the "mc" name: L_mc is the mean over the resolution and blur levels
        result.losses["ff_mc"] = config.lambda_ff * config.lambda_mc * means["mc"]
        result.losses["ff_cr"] = config.lambda_ff * config.lambda_cr * means["cr"]
    if use_cam:
        result.losses["cf_mc"] = config.lambda_cf * config.lambda_mc * means["cam_mc"]
        result.losses["cf_cr"] = config.lambda_cf * config.lambda_cr * means["cam_cr"]
    return result
