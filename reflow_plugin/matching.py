"""Self-correction flow matching losses (paper section 3.3, DESIGN.md section 5), per direction.

A direction a -> b has a SOURCE view a (composited: its render, depth, alpha and flow channels
towards b) and a TARGET frame b: its ground truth I_b always; its render (for L_cr) only when b
was composited too (`pair_mode both`, the paper's pairwise batch); in `pair_mode partner` (ours)
b is only deformed and projected, which is all the full flow needs. Per direction:

    full flow F   (from view a's flow channels)        camera flow F^cam (from view a's depth)
    L_mc   = photo(I_b warped by F, I_a)               L^cam_mc = photo(I_b warped by F^cam, I_a)   on static pixels
    L_cr   = photo(render_b warped by F, I_a)          L^cam_cr = photo(render_b warped by F^cam, I_a) on static pixels
             (only with render_b)                                (only with render_b)

on the pixels where the flow is valid and lands inside image b (and, with the `occlusion`
component, passes the forward-backward test against the reverse direction's full flow; with
`cam_occlusion`, the camera-flow terms pass the same test on the two camera flows; both need
the reverse direction, so only `pair_mode both` runs them and a training run refuses them in
`pair_mode partner` before its initial cloud is built, `check_occlusion_mode`; with
`full_flow_dynamic_only`, ours, L_mc and L_cr only on dynamic pixels (`dynamic_threshold`), each
pixel weighted as in the loss over all pixels). Static pixels: the rendered dynamic-ness channel (1 for
dynamic Gaussians) below 0.5 of the pixel's opacity; with `cam_target_static` (the paper's
masking) the pixel must also land on a static pixel of b (b's rendered dynamic share, or b's
motion mask when b was not composited); with motion masks given for a direction (the coarse
stage, where the dynamic Gaussians are hidden and that channel is 0 everywhere) the pixel must
also lie outside a's mask and sample b outside b's. Directions are averaged; the returned terms are already
weighted:

    ff_mc = lambda_ff * lambda_mc * L_mc        ff_cr = lambda_ff * lambda_cr * L_cr
    cf_mc = lambda_cf * lambda_mc * L^cam_mc    cf_cr = lambda_cf * lambda_cr * L^cam_cr

with lambda_cr = cross_time_ratio * lambda_mc (paper: 0.1). `blur_sigmas` (ours) adds
motion-consistency terms on blurred images, averaged with the full-resolution one: a photometric
loss only "sees" motion within about a pixel of its sample, blur widens that range.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from torch import Tensor

from baselines.data import Camera
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
    full_flow_min_share: float = STATIC_BELOW  # with full_flow_dynamic_only: a pixel's dynamic share at least this
    # ... or min_share x the view's top share where no pixel reaches it (dynamic_threshold): an
    # experiment knob, no flag (ReFlowParams stays at 40 fields): it acts on DAVIS views too and no
    # benchmark run has measured it (docs/REAL_CAPTURES.md, "Basketball as a wide rig")
    full_flow_relative_gate: bool = False
    cam_occlusion: bool = False  # forward-backward test on the two camera flows
    cam_target_static: bool = False  # camera-flow terms only where the pixel lands on a static pixel of b

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


@dataclass
class FlowPair:
    """One direction a -> b of flow matching.

    Attributes:
        source: view a, composited (extras[FLOW_KEY] for full flow, extras[DYNAMIC_KEY] for the
            static mask of camera flow and the dynamic-only options).
        target: camera b (its image is I_b).
        target_render: [H, W, 3] render of b (L_cr terms), or None when b was not composited.
        target_dynamic: [H, W] float dynamic share of b's pixels (the target-side static mask), or None.
        reverse: index of the direction b -> a in the same list (occlusion tests), or None.
        moving: ([H, W] bool mask of a, [H, W] bool mask of b) (True = moving), or None: camera
            flow keeps a's masked pixels out and those sampling b's mask (the coarse stage).
    """

    source: ViewRender
    target: Camera
    target_render: Tensor | None = None
    target_dynamic: Tensor | None = None
    reverse: int | None = None
    moving: tuple[Tensor, Tensor] | None = None


def check_occlusion_mode(occlusion: bool, cam_occlusion: bool, pair_mode: str) -> None:
    """Refuse an occlusion test the pair mode cannot run (ValueError, one line naming the switches).

    Both tests compare a direction a -> b with the reverse direction b -> a, which only
    `pair_mode both` renders; in `pair_mode partner` b is projected, never composited, so there
    is no reverse flow and the switch would be recorded as on while doing nothing."""
    named = [name for name, on in (("occlusion", occlusion), ("cam_occlusion", cam_occlusion)) if on]
    if named and pair_mode != "both":
        raise ValueError(f"--enable {','.join(named)} needs --pair_mode both (the forward-backward test compares "
                         f"the pair's two rendered directions; --pair_mode {pair_mode} renders one view only)")


def _static_pixels(view: ViewRender) -> Tensor:
    """[H, W] bool: pixels whose rendered dynamic share (extras[DYNAMIC_KEY] / alpha) is below STATIC_BELOW."""
    return dynamic_share(view) < STATIC_BELOW


def dynamic_share(view: ViewRender) -> Tensor:
    """[H, W] rendered dynamic share of each pixel: extras[DYNAMIC_KEY] / alpha."""
    return view.extras[DYNAMIC_KEY][..., 0] / view.alpha[..., 0].clamp_min(1e-6)


def dynamic_threshold(share: Tensor, usable: Tensor, min_share: float, relative: bool = True) -> tuple[Tensor, Tensor]:
    """(threshold, the view's top share): the dynamic share a pixel needs to enter full flow matching.

    `min_share` itself when some `usable` pixel ([H, W] bool; share [H, W]) reaches it; otherwise
    min_share times the largest share among the usable pixels, at least STATIC_BELOW: a pixel must
    be as dynamic as min_share of the view's most dynamic one, and majority-dynamic. Dense dynamic
    Gaussians reach min_share 0.9 and keep the fixed gate (NVIDIA Balloon1 -r 8: top share >= 0.9998
    in all 200 logged directions); a single layer of them cannot (their opacity starts at 0.9, and
    the keyframe seeds' temporal windows scale it below that between keyframes): CMU Panoptic
    basketball at -r 4 with the default schedule, top shares 0.69-0.82 and no pixel >= 0.9 in any
    logged iteration. A min_share below STATIC_BELOW is taken as given. `relative=False`: min_share
    in every view (the default: MatchingConfig.full_flow_relative_gate off). No device sync (tensors)."""
    top = torch.where(usable, share, torch.zeros_like(share)).max().detach()
    if not relative:
        return torch.full_like(top, min_share), top
    relative = (min_share * top).clamp(min(STATIC_BELOW, min_share), min_share)
    return torch.where(top >= min_share, torch.full_like(relative, min_share), relative), top


def _off_moving(moving: tuple[Tensor, Tensor], flow: Tensor) -> Tensor:
    """[H, W] bool: the source pixel lies outside its motion mask (moving[0]) and its sample in the
    target (at q + flow, bilinear: all four neighbours) outside the target's mask (moving[1])."""
    lands, _ = backward_warp(moving[1].to(flow.dtype).unsqueeze(-1), flow)
    return ~moving[0] & (lands[..., 0] < 1e-6)


def pair_losses(views: list[ViewRender], config: MatchingConfig, use_full: bool, use_cam: bool,
                blurred: Callable[[int, float], tuple[Tensor, Tensor]] | None = None,
                moving: Sequence[Tensor] | None = None) -> PairResult:
    """Flow matching losses of a 2-view batch, both views composited (`pair_mode both`).

    Args:
        views: the pair's two composited views; with `use_full` each carries extras[FLOW_KEY]
            ([H, W, 7] flow channels towards the other view), with `use_cam` or the dynamic-only
            options extras[DYNAMIC_KEY] ([H, W, 1]).
        blurred: (view index k, sigma) -> (blurred I_other, blurred I_k), for `blur_sigmas`.
        moving: per view [H, W] bool motion masks (True = moving) kept out of camera-flow matching.
    """
    pairs = []
    for k in range(2):
        b = views[1 - k]
        target_dynamic = dynamic_share(b) if config.cam_target_static and use_cam else None
        masks = None if moving is None else (moving[k], moving[1 - k])
        pairs.append(FlowPair(views[k], b.camera, b.image, target_dynamic, reverse=1 - k, moving=masks))
    return flow_losses(pairs, config, [use_full] * 2, [use_cam] * 2, blurred)


def flow_losses(pairs: list[FlowPair], config: MatchingConfig, use_full: list[bool], use_cam: list[bool],
                blurred: Callable[[int, float], tuple[Tensor, Tensor]] | None = None) -> PairResult:
    """Flow matching losses of the given directions (see the module docstring).

    Args:
        use_full, use_cam: per direction, whether its full-flow / camera-flow terms are computed.
        blurred: (direction index k, sigma) -> (blurred I_b, blurred I_a), for `blur_sigmas`.
    """
    result = PairResult()
    terms = _Terms()
    full_flows = [full_flow(p.source.extras[FLOW_KEY], p.source.alpha, config.min_alpha) if use_full[k] else None
                  for k, p in enumerate(pairs)]
    camera_flows = [camera_flow(p.source.depth, p.source.alpha, p.source.camera.K, p.source.camera.viewmat,
                                p.target.K, p.target.viewmat, config.min_alpha) if use_cam[k] else None
                    for k, p in enumerate(pairs)]
    for k, pair in enumerate(pairs):
        a = pair.source
        gt_a = a.camera.image
        with_render = pair.target_render is not None
        # warp ground truth and render together
        sources = torch.cat((pair.target.image, pair.target_render), dim=-1) if with_render else pair.target.image
        direction = Direction()
        blur_sigmas = config.blur_sigmas if use_full[k] and blurred is not None else ()
        blurred_pairs = [blurred(k, sigma) for sigma in blur_sigmas]  # (blurred I_b, blurred I_a)
        if use_full[k]:
            flow, valid = full_flows[k]
            # I_b (and render_b) and the blurred I_b share the flow: one sampling call for all
            stacked = torch.cat((sources, *[b for b, _ in blurred_pairs]), dim=-1) if blurred_pairs else sources
            warped_all, inside = backward_warp(stacked, flow)
            warped = warped_all[..., :sources.shape[-1]]
            mask = valid & inside
            reverse = full_flows[pair.reverse] if pair.reverse is not None else None
            if config.occlusion and reverse is not None:
                mask = mask & occlusion_mask(flow, reverse[0], config.occlusion_alpha1, config.occlusion_alpha2)
            weight: Tensor | float = 1.0
            top = None
            if config.full_flow_dynamic_only:
                # same per-pixel weight as over all pixels: the mean over the dynamic pixels times their share
                share = dynamic_share(a)
                threshold, top = dynamic_threshold(share, mask, config.full_flow_min_share,
                                                   relative=config.full_flow_relative_gate)
                dynamic = mask & (share >= threshold)
                weight = dynamic.sum().float() / mask.sum().clamp_min(1).float()
                covered, mask = mask, dynamic
            terms.add("mc", warped[..., :3], gt_a, mask, weight)
            if with_render:
                terms.add("cr", warped[..., 3:], gt_a, mask, weight)
            if blurred_pairs:
                start = sources.shape[-1]
                for blur_b, blur_a in blurred_pairs:
                    width = blur_b.shape[-1]
                    terms.add("mc", warped_all[..., start:start + width], blur_a, mask, weight)
                    start += width
            direction.flow, direction.valid, direction.warped = flow, mask, warped[..., :3]
            if top is None:
                result.metrics[f"flow_valid_{k}"] = float(mask.float().mean())
            else:  # one device sync: the valid share, the share before the dynamic gate, the view's top share
                values = torch.stack((mask.float().mean(), covered.float().mean(), top.float())).tolist()
                for name, value in zip(("flow_valid", "flow_covered", "flow_top_share"), values):
                    result.metrics[f"{name}_{k}"] = value
        if use_cam[k]:
            flow_c, valid_c = camera_flows[k]
            warped_c, inside = backward_warp(sources, flow_c)
            mask = valid_c & inside & _static_pixels(a)
            if pair.moving is not None:
                mask = mask & _off_moving(pair.moving, flow_c)
            if pair.target_dynamic is not None:
                with torch.no_grad():  # the target's dynamic share where each pixel lands
                    landed = backward_warp(pair.target_dynamic.unsqueeze(-1).to(flow_c.dtype), flow_c)[0][..., 0]
                mask = mask & (landed < STATIC_BELOW)
            reverse = camera_flows[pair.reverse] if pair.reverse is not None else None
            if config.cam_occlusion and reverse is not None:
                mask = mask & occlusion_mask(flow_c, reverse[0], config.occlusion_alpha1, config.occlusion_alpha2)
            terms.add("cam_mc", warped_c[..., :3], gt_a, mask)
            if with_render:
                terms.add("cam_cr", warped_c[..., 3:], gt_a, mask)
            direction.cam_flow, direction.static = flow_c, mask
        result.directions.append(direction)
    if not terms.names:
        return result
    means = terms.means(config.ssim_weight)
    # blurred terms share the "mc" name: L_mc is the mean over the resolution and blur levels
    for name, key, weight in (("mc", "ff_mc", config.lambda_ff * config.lambda_mc),
                              ("cr", "ff_cr", config.lambda_ff * config.lambda_cr),
                              ("cam_mc", "cf_mc", config.lambda_cf * config.lambda_mc),
                              ("cam_cr", "cf_cr", config.lambda_cf * config.lambda_cr)):
        if name in means:
            result.losses[key] = weight * means[name]
    return result
