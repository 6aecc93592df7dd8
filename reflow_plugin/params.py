"""`ReFlowParams`: the plugin's config group (flags and config-file keys, like every 4DGS group).

Set from config files (``ReFlowParams = dict(lambda_ff=1.0)``, see ``arguments/*/reflow.py``) or
the command line (``--lambda_ff 1.0``; field names are the flag names). Components (the ablation
switches) are not here: they are ``--disable``/``--enable`` of the plugin (see plugin.py).

Paper values (appendix A.4): lambda_ff 5.0 / lambda_cf 0.3 for NVIDIA-like scenes, 1.0 / 0.1 for
HyperNeRF-like scenes; the cross-time weight is 0.1 x the motion-consistency weight; photo =
0.8 L1 + 0.2 (1 - SSIM) as in 3DGS. Everything else is ours and documented per field.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from arguments import param

LABEL_SOURCES = ("auto", "masks", "estimate", "none")
UPGRADE_LABELS = ("auto", "motion", "checkpoint")
STATIC_DECODERS = ("auto", "none", "triplane", "field")
CANONICAL_PROVIDERS = ("auto", "depth", "flow")
FULL_FLOW_REGIONS = ("all", "dynamic")
PAIR_MODES = ("partner", "both")

# --- fixed values: flags until 2026-11-26, now constants nobody should tune (docs/PARAMETERS.md) ---
PHOTO_SSIM_WEIGHT = 0.2  # photometric loss 0.8 L1 + 0.2 (1 - SSIM): the paper's and 3DGS's
FLOW_MIN_ALPHA = 0.5  # a pixel carries flow when at least half of it is covered by Gaussians
OCCLUSION_ALPHA1, OCCLUSION_ALPHA2 = 0.01, 0.5  # the classic forward-backward test's constants (component occlusion)
DYNAMIC_INIT_OPACITY = 0.9  # dynamic seeds come from a frame where the object is visible (4DGS: 0.1)
DYNAMIC_AABB_MARGIN = 0.25  # dynamic HexPlane box: the dynamic points' box grown by this fraction per side
TIME_SCALE_LR = 0.005  # learning rate of the keyframe seeds' log temporal window widths
WINDOW_CULL = 1e-3  # keyframe copies whose window weight is below this are not deformed: exact below 1/255
FLOW_CLOUD_MAX_DEPTH_ERROR = 0.02  # a flow-provider canonical cloud against the SfM points (canonical_construction.py)
# The flow provider's partners on a sequence: frames n +- 1 .. n +- spread (canonical/providers.py,
# fused_depth). Not a flag: an A/B switch until the real-capture benchmark has measured it in training
# (docs/REAL_CAPTURES.md, "The canonical space on DAVIS").
# Likewise the finest pyramid level of its DIS flow (0 = full resolution; unset: the preset's 1, half).
FLOW_SPREAD_SWITCH = "REFLOW4DGS_FLOW_SPREAD"
FLOW_FINEST_SWITCH = "REFLOW4DGS_FLOW_FINEST"


def _env_int(name: str, default: int | None, low: int, meaning: str) -> int | None:
    import os

    text = os.environ.get(name, "").strip()
    if not text:
        return default
    if not text.isdigit() or int(text) < low:
        raise ValueError(f"{name}={text!r}: must be an integer >= {low} ({meaning})")
    return int(text)


def flow_spread_from_env() -> int:
    """`REFLOW4DGS_FLOW_SPREAD` as an integer >= 1 (unset or empty: 1, the time neighbours only);
    anything else is a ValueError naming the variable."""
    return _env_int(FLOW_SPREAD_SWITCH, 1, 1, "1 = the time neighbours only")


def flow_finest_from_env() -> int | None:
    """`REFLOW4DGS_FLOW_FINEST` as an integer >= 0 (unset or empty: None, DIS's preset); anything
    else is a ValueError naming the variable."""
    return _env_int(FLOW_FINEST_SWITCH, None, 0, "the finest DIS pyramid level, 0 = full resolution")


def _removed(what: str, why: str) -> str:
    return f"on 2026-11-26 ({what}; measured: {why}; docs/PARAMETERS.md)"


def _fixed(what: str) -> str:
    return f"on 2026-11-26: now fixed, {what} (reflow_plugin/params.py; docs/PARAMETERS.md)"


def resolve_static_decoder(choice: str, separation: bool) -> str:
    """The static decoder a run uses: `auto` is the field with the separation component (ahead of
    `none` on every capture and simulator suite it was measured on: docs/PARAMETERS.md) and none
    without it (4DGS's one network then deforms every Gaussian: no static branch). An explicit
    decoder without separation is refused (ValueError naming the flag)."""
    if choice == "auto":
        return "field" if separation else "none"
    if choice != "none" and not separation:
        raise ValueError(f"--static_decoder {choice} needs the separation component; "
                         "drop --disable separation or the flag")
    return choice


def _non_negative(value: float) -> str | None:
    return None if value >= 0 else f"must be >= 0, got {value}"


def _positive(value: float) -> str | None:
    return None if value > 0 else f"must be > 0, got {value}"


def _fraction(value: float) -> str | None:
    return None if 0.0 <= value <= 1.0 else f"must lie in [0, 1], got {value}"


def _sigmas(value: list[float]) -> str | None:
    bad = [s for s in value if not s > 0]
    return f"blur sigmas must be > 0, got {bad}" if bad else None


def _grid_side(value: int) -> str | None:
    return None if value == 0 or value >= 2 else "must be 0 (off) or >= 2"


def _clip_len(value: int) -> str | None:
    # the alignment refused 1 too (canonical/coarse_to_fine.py), but only after the masks and depth fits
    return None if value >= 2 else f"must be at least 2 (a clip pairs its frames), got {value}"


def _edge_ratio(value: float) -> str | None:
    # a depth ratio of at most 1 is exceeded by every pixel whose neighbourhood is not flat: all "edges"
    return None if value == 0 or value > 1 else f"must be 0 (off) or > 1, got {value}"


def _nonzero_ints(value: list[int]) -> str | None:
    bad = [o for o in value if not isinstance(o, int) or isinstance(o, bool) or o == 0]
    if bad or not value:
        return f"must be a non-empty list of non-zero integers, got {value}"
    return None


def _slow_offsets(value: list[int]) -> str | None:
    if value == [0] or not value:  # 0 alone: the slow pairing off
        return None
    problem = _nonzero_ints(value)
    return problem and f"{problem} (or 0 alone: off)"


@dataclass
class ReFlowParams:
    """Weights, schedule and options of ReFlow (paper sections 3.2-3.4, appendix A)."""

    # fields taken out (experiments that did not pay, or constants): a config file or flag naming
    # one gets this line (arguments.layers.removed_note); the figures are in docs/PARAMETERS.md
    REMOVED_FIELDS: ClassVar[dict[str, str]] = {
        "relabel_every": _removed("labels that change during training", "neutral: real-priors suite every "
                                  "scene within 0.1 dB, mean 24.88 vs 24.94"),
        "relabel_residual": _removed("the residual threshold of --relabel_every", "see relabel_every"),
        "relabel_min_views": _removed("the view count of --relabel_every", "see relabel_every"),
        "promote_residual": _removed("static Gaussians promoted after the coarse stage", "neutral: real-priors "
                                     "suite mean 24.85 vs 24.91"),
        "box_labels": _removed("every Gaussian in the dynamic box dynamic (a diagnostic)", "umbrella -1.1 dB, "
                               "truck -0.8 dB overall at 3-4x the time"),
        "pair_max_motion": _removed("partners limited by camera motion", "neutral: +0.08 dB on the embedded scene"),
        "flow_blur_region": _removed("blurred motion-consistency terms on dynamic pixels only", "-1.35 dB on the "
                                     "embedded scene"),
        "full_flow_static_grad": _removed("--no-full_flow_static_grad detached static Gaussians' flow channels",
                                          "-0.14 dB on the embedded scene; the paper's gradient is kept"),
        "dynamic_warmup": _removed("fine iterations with the dynamic deformation frozen (default 0)",
                                   "never on; --dynamic_settle_fraction holds the dynamic Gaussians instead"),
        "canonical_shift": _removed("a per-frame depth shift in the pairwise alignment", "it trades against the "
                                    "scale and flattens the depth of noisy pointmaps"),
        "dynamic_scale_free": _removed("--no-dynamic_scale_free (the capped rates alone)", "the scale-free "
                                       "branch is always on: +0.39 dB on Balloon1, bit-identical at extent <= 1"),
        "photo_ssim_weight": _fixed("PHOTO_SSIM_WEIGHT = 0.2 (the paper's 0.8 L1 + 0.2 D-SSIM)"),
        "flow_min_alpha": _fixed("FLOW_MIN_ALPHA = 0.5"),
        "occlusion_alpha1": _fixed("OCCLUSION_ALPHA1 = 0.01"),
        "occlusion_alpha2": _fixed("OCCLUSION_ALPHA2 = 0.5"),
        "dynamic_aabb_margin": _fixed("DYNAMIC_AABB_MARGIN = 0.25"),
        "dynamic_init_opacity": _fixed("DYNAMIC_INIT_OPACITY = 0.9"),
        "time_scale_lr": _fixed("TIME_SCALE_LR = 0.005"),
        "window_cull": _fixed("WINDOW_CULL = 1e-3, exact"),
        "cam_flow_target_static": _fixed("always on (the paper masks both sides; +0.02 dB)"),
        "coarse_static_only": _fixed("always on (the coarse stage fits the static scene alone)"),
        "protect_dynamic": _fixed("always on (dynamic Gaussians are never pruned)"),
        "dynamic_zero_init": _fixed("always on (the dynamic branch starts at the canonical place)"),
        "relative_time": _fixed("always on (keyframe seeds deformed at t - t_keyframe)"),
        "anchor_keyframes": _fixed("always on (without the anchor the flow loss dragged every copy off its "
                                   "frame: EPE-dynamic 4.30 vs 0.74 px)"),
    }

    # --- loss weights (paper) ---
    lambda_ff: float = param(5.0, "weight of full flow matching (paper: 5.0 NVIDIA-like, 1.0 HyperNeRF-like)",
                             check=_non_negative)
    lambda_cf: float = param(0.3, "weight of camera flow matching (paper: 0.3 NVIDIA-like, 0.1 HyperNeRF-like)",
                             check=_non_negative)
    lambda_mc: float = param(1.0, "motion-consistency weight inside each flow matching term", check=_non_negative)
    cross_time_ratio: float = param(0.1, "cross-time rendering weight as a multiple of lambda_mc (paper: 0.1)",
                                    check=_non_negative)
    lambda_ext: float = param(1.0, "weight of the external-flow L1 loss (component ext_flow, the paper's "
                                   "'Ours (External Flow)' comparison), per pixel of flow", check=_non_negative)
    # --- pairs and flow ---
    pair_window: int = param(2, "largest distance, in training frames, between the two frames of a pair",
                             check=_positive)
    pair_mode: str = param("partner", "partner (ours): each iteration renders the host's one view a and only "
                                      "deforms + projects a nearby frame b (what L_mc and camera flow of a -> b "
                                      "need); no L_cr (it needs b's render). both (the paper): both frames "
                                      "rendered, both directions, L_cr; the occlusion components need both",
                           choices=PAIR_MODES)
    flow_blur_sigmas: list[float] = param([2.0, 4.0], "extra motion-consistency terms on images blurred with "
                                              "these Gaussian sigmas in pixels (ours, beyond the paper: a wider "
                                              "capture range for large motion); [] = the paper's loss",
                                          check=_sigmas)
    full_flow_region: str = param("dynamic", "pixels full flow matching is evaluated on: dynamic (ours, the default: "
                                             "only where the rendered dynamic share is >= --full_flow_min_share, each pixel weighted as "
                                             "in the loss over all pixels; static pixels are left to camera flow "
                                             "matching; all pixels without separation) or all (the paper)", choices=FULL_FLOW_REGIONS)
    full_flow_min_share: float = param(0.9, "ours, with --full_flow_region dynamic: a pixel enters full flow "
                                             "matching when its rendered dynamic share is at least this (mixed "
                                             "pixels at the object's edge blend static Gaussians in; 0.5 before: "
                                             "-0.5 dB on the suite, all of it a band around the moving objects)",
                                       check=_fraction)
    flow_every: int = param(1, "compute the flow-matching terms (and their flow channels) every this many "
                               "iterations only: a cost knob of the accuracy-versus-time sweep",
                            check=_positive)
    cam_flow_min_motion: float = param(0.05, "skip camera-flow losses on pairs whose cameras move less than "
                                             "this many pixels (estimated at the scene's median depth)",
                                       check=_non_negative)
    # --- schedule (appendix A.4; ours where noted) ---
    dynamic_settle_fraction: float = param(0.5, "ours: fraction of the fine stage during which the dynamic "
                                                "Gaussians' own parameters (opacity, colour, scale, ...) are held "
                                                "fixed, so the losses can only be lowered by MOVING them: with an "
                                                "unlearned motion, full flow matching otherwise fades them out",
                                           check=_fraction)
    curriculum_fraction: float = param(0.5, "ours, with a single reference frame (dynamic_keyframes 1): "
                                             "fraction of the fine stage over which pairs spread from the "
                                             "reference frame to the whole sequence (0 = all frames at once)",
                                       check=_fraction)
    # --- separated model (paper 3.2.2, appendix A.2) ---
    static_decoder: str = param("auto", "decoder of static Gaussians: auto (field with the separation component, "
                                        "none without it), none (canonical values, cheapest), triplane (the "
                                        "paper's time-invariant spatial planes + MLP) or field (ours: a 4DGS "
                                        "deformation field of the whole scene at 4DGS's rates)",
                                choices=STATIC_DECODERS)
    dynamic_lr_scale: float = param(10.0, "ours: learning-rate multiplier of the dynamic branch (deformation MLP "
                                          "and HexPlane); 4DGS's rates learn a deformation of a whole scene, "
                                          "too slowly for an object crossing the view", check=_positive)
    dynamic_lr_extent_cap: float = param(1.0, "ours: the dynamic branch's rates use min(scene extent, this) where "
                                              "4DGS multiplies them by the extent: with the 10x multiplier, the "
                                              "embedded scene scaled 6x (extent 3.4) diverged to NaN within 200 "
                                              "fine iterations (0 = 4DGS's extent factor, uncapped)",
                                         check=_non_negative)
    disparity_field: int = param(4, "ours: the dataset's monocular disparity gets a smooth per-frame correction "
                                    "(a bilinear field on this many control values per side, fitted to the "
                                    "sparse static points after the affine fit and kept only where it lowers "
                                    "the error on held-out points; reflow_plugin/disparity_field.py) before the "
                                    "masks, the canonical space and the seeds read it; 0 = the affine fit alone",
                                 check=_grid_side)
    # --- labels and seeding ---
    label_source: str = param("auto", "where static/dynamic labels come from: auto (canonical init, else the "
                                      "dataset's motion masks, else estimated masks), masks, estimate, none",
                              choices=LABEL_SOURCES)
    mask_offsets: list[int] = param([-2, -1, 1, 2], "estimated motion masks: each training frame is tested "
                                                    "against the frames this many places away in time order "
                                                    "(the per-pixel median over the pairs is thresholded; "
                                                    "wider offsets see slow motion, e.g. an object turning "
                                                    "in place)", check=_nonzero_ints)
    mask_slow_offsets: list[int] = param([-8, -6, -4, 4, 6, 8],
                                         "estimated motion masks, ours: a second test against the frames "
                                         "this many places away (2 px of raw error needed), adding the "
                                         "pixels it flags that the first does not call static: objects that "
                                         "move a fraction of a pixel per frame, e.g. an umbrella turning in "
                                         "place; 0 = off (the first test alone)",
                                         check=_slow_offsets)
    label_vote: float = param(0.5, "an initial point is dynamic when it lies inside the motion mask in at "
                                   "least this fraction of the training views that see it", check=_fraction)
    seed_edge_ratio: float = param(1.1, "ours: keyframe seeds on depth edges (the 3x3 neighbourhood's depths "
                                        "span more than this ratio: a monocular depth map's soft edges put "
                                        "such pixels between the object and the background) take the nearest "
                                        "depth of their 5x5 neighbourhood (README: \"Seeds on soft depth edges\"); 0 = "
                                        "the depth as it is",
                                   check=_edge_ratio)
    seed_points: int = param(20_000, "most dynamic points seeded inside the motion masks, over all keyframes "
                                     "(0 = no seeding)", check=_non_negative)
    dynamic_keyframes: int = param(8, "ours: frames the dynamic points are seeded from, spread over the "
                                      "sequence, each point in a temporal opacity window around its frame; "
                                      "1 = the paper's single reference frame", check=_positive)
    # --- upgrading a 4DGS checkpoint (--start_checkpoint OLD/point_cloud/iteration_N) ---
    upgrade_labels: str = param("auto", "labels of a loaded point_cloud folder: motion (from the deformation "
                                        "magnitude over the training times, static Gaussians baked at their "
                                        "time average), checkpoint (its deformation_table.pth), auto (checkpoint "
                                        "when a ReFlow run wrote it, else motion)", choices=UPGRADE_LABELS)
    upgrade_motion_threshold: float = param(0.005, "a loaded 4DGS Gaussian is dynamic when its centre moves more "
                                                   "than this fraction of the scene extent from its time average",
                                            check=_non_negative)
    # --- complete canonical space (paper 3.2.1, appendix A.1; reflow_plugin.canonical) ---
    canonical_provider: str = param("auto", "pointmap provider of the canonical space: depth (the dataset's "
                                            "disparity), flow (DIS flow triangulated with the cameras), auto "
                                            "(depth when every frame has disparity, else flow)",
                                    choices=CANONICAL_PROVIDERS)
    canonical_align: bool = param(True, "global coarse-to-fine alignment of the pointmaps; --no-canonical_align "
                                        "merges the raw per-frame pointmaps (the paper's 'w/o align' ablation)")
    canonical_clip_len: int = param(25, "frames per clip of the pairwise coarse-to-fine alignment (the first of "
                                        "each is a keyframe; paper: 25-30); not read where the inverse-depth "
                                        "refinement runs instead (depth provider with sparse points or the "
                                        "dataset's near/far bounds)", check=_clip_len)
    canonical_window: int = param(4, "ours: inside a clip, frames at most this far apart are paired (plus "
                                     "every frame with its keyframe)", check=_positive)
    canonical_voxel: float = param(0.01, "voxel side of the fused static cloud as a fraction of the median "
                                         "depth (0 = no downsampling)", check=_non_negative)
    canonical_max_points: int = param(20_000, "at most this many fused static points: the voxel grows in x1.25 "
                                              "steps until the cloud fits (noisy monocular depth thickens "
                                              "surfaces; 0 = no limit; not applied with --canonical_voxel 0, "
                                              "which keeps every point)", check=_non_negative)
    canonical_consistency: float = param(0.05, "ours: multi-view test of the fused static points: a point that "
                                               "more training frames see through (their aligned depth farther "
                                               "than it by this relative tolerance) than agree with it is "
                                               "dropped (floaters of per-frame depth errors; 0 = off)",
                                         check=_non_negative)
    canonical_max_fit_residual: float = param(0.1, "ours, monocular disparity with sparse points: when the "
                                                   "per-frame fits of the disparity to the sparse points leave a "
                                                   "median relative depth error above this on points held out by "
                                                   "image region (canonical/check.py), the dense "
                                                   "cloud is not used (the check fails: the host's cloud + part 1 "
                                                   "seeds); 0 = no limit", check=_non_negative)
    canonical_max_depth_error: float = param(0.06, "ours, with sparse points (any provider): when the canonical "
                                                  "cloud's median relative depth error against them (per covered "
                                                  "4-px cell) is above this, the dense cloud is not used (the "
                                                  "host's cloud + part 1 seeds); 0 = no limit of its own (a cloud of the "
                                                  "flow provider still has to agree within 2%; --no-canonical_check "
                                                  "lifts every check)", check=_non_negative)
    canonical_iters: int = param(300, "Adam iterations of each pairwise alignment (keyframe graph, each clip); "
                                      "the inverse-depth refinement runs a fixed 50", check=_non_negative)
    canonical_check: bool = param(True, "check the canonical cloud before training (views, depth against the "
                                        "sparse points or bounds, dynamic spread) and fall back when it fails; "
                                        "--no-canonical_check keeps a failing cloud (with the warning), e.g. to "
                                        "measure raw 'w/o align' on monocular disparity")
    canonical_cache: bool = param(True, "reuse the canonical space cached in <model>/reflow/canonical when the "
                                        "dataset, masks and settings are unchanged")
    # --- diagnostics ---
    flow_vis_every: int = param(500, "write a flow-matching panel [I_a | I_b warped | I_b | error | flow] "
                                     "every this many fine iterations (0 = never)", check=_non_negative)
