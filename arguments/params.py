"""The 4DGS parameter groups as typed dataclasses (4DGS names and defaults), plus the run-level
flags of 4DGS's train.py and render.py.

Every field of 4DGS's ``ModelParams``, ``PipelineParams``, ``OptimizationParams`` and
``ModelHiddenParams`` exists under its 4DGS name with its 4DGS default. Fields marked
``compat`` are accepted only so that 4DGS config files and command lines keep working: they have
no effect here, and a non-default value logs one warning. Fields marked ``ours`` are additions of
this project (``ModelParams.dataset_type/force_dataset_points``, ``PipelineParams.backend``, ``PipelineParams.device``,
``OptimizationParams.seed``, and ``RunParams.plugin/disable/enable/log_every``).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from .fields import param

BACKENDS = ("auto", "cpu", "reference", "gsplat")
MLP_PRECISIONS = ("auto", "float32", "bfloat16")
DATASET_TYPES = ("auto", "nvidia", "dnerf", "hypernerf", "colmap", "panoptic", "synthetic")
KPLANES_KEYS = ("grid_dimensions", "input_coordinate_dim", "output_coordinate_dim", "resolution")

_COMPAT_4DGS_UNUSED = "no effect in 4DGS either"
# the highest SH degree the renderer evaluates (baselines/render/sh.py, as 3DGS's rasterizer)
MAX_SH_DEGREE = 3


def _check_device(value: str) -> str | None:
    if re.fullmatch(r"auto|cpu|cuda(:\d+)?", value):
        return None
    return f"expected auto, cpu, cuda or cuda:N, got {value!r}"


def _check_kplanes(value: dict[str, Any]) -> str | None:
    unknown = sorted(set(value) - set(KPLANES_KEYS))
    if unknown:
        return f"unknown key(s) {unknown}; known: {list(KPLANES_KEYS)}"
    missing = [k for k in KPLANES_KEYS if k not in value]
    if missing:
        return f"missing key(s) {missing}"
    for key in ("grid_dimensions", "input_coordinate_dim", "output_coordinate_dim"):
        v = value[key]
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            return f"{key} must be a positive int, got {v!r}"
    res = value["resolution"]
    if (not isinstance(res, (list, tuple))
            or not all(isinstance(r, int) and not isinstance(r, bool) and r > 0 for r in res)):
        return f"resolution must be a list of positive ints, got {res!r}"
    if len(res) != value["input_coordinate_dim"]:
        return (f"resolution has {len(res)} entries but input_coordinate_dim is "
                f"{value['input_coordinate_dim']} (x, y, z, t)")
    return None


def _check_multires(value: list[int]) -> str | None:
    if not value or any(m < 1 for m in value):
        return f"expected a non-empty list of positive ints, got {value!r}"
    return None


def _check_non_negative(value: float) -> str | None:
    return None if value >= 0 else f"must be >= 0, got {value}"


def _check_fraction(value: float) -> str | None:
    return None if 0.0 <= value <= 1.0 else f"must lie in [0, 1], got {value}"


def _check_sh_degree(value: int) -> str | None:
    # a higher degree trained until the active degree reached it (iteration 4000), then stopped
    return None if 0 <= value <= MAX_SH_DEGREE else f"must be in [0, {MAX_SH_DEGREE}], got {value}"


def _check_resolution(value: int) -> str | None:
    # the readers refused 0 and other negatives too, but only once the run folder was claimed
    return None if value == -1 or value > 0 else f"expected -1, 1, 2, 4, 8 or a width > 0, got {value}"


def _check_render_iteration(value: int) -> str | None:
    return None if value == -1 or value >= 0 else f"expected a saved iteration or -1 (the latest), got {value}"


def _check_positive(value: int) -> str | None:
    return None if value > 0 else f"must be > 0, got {value}"


def _check_unsupported(value: bool) -> str | None:
    return None if not value else "is not supported (a 4DGS experiment labelled useless there); set it to False"


def _check_grid_pe(value: int) -> str | None:
    return None if value == 0 or value > 1 else f"must be 0 (off) or > 1, got {value}"


def _check_seed(value: int) -> str | None:
    return None if 0 <= value < 2**32 else f"must be in [0, 2**32 - 1] (numpy's seed range), got {value}"


@dataclass
class ModelParams:
    """Dataset loading and model size (4DGS "Loading Parameters")."""

    sh_degree: int = param(3, "maximum spherical-harmonics degree of the Gaussians' colours (0 to 3)",
                           check=_check_sh_degree)
    source_path: str = param("", "dataset directory (empty: the embedded synthetic scene)",
                             short="s")
    model_path: str = param("", "output directory (empty: output/<expname>)", short="m")
    images: str = param("images", "image sub-directory of the dataset", short="i")
    resolution: int = param(-1, "image size: -1 auto (width capped at 1600 px), 1/2/4/8 = "
                                "downscale factor, other values = target width in pixels",
                            short="r", check=_check_resolution)
    white_background: bool = param(True, "background colour white (else black) for renders and RGBA ground "
                                         "truth; unless a flag or config file sets it, the dataset family's "
                                         "(white: the simulator's scenes and D-NeRF; black: real captures), "
                                         "even with --configs none", short="w")
    data_device: str = param("cuda", "4DGS: device holding the images; use --device here",
                             compat=True)
    eval: bool = param(True, "hold out test views (the dataset's split, or every llffhold-th "
                             "frame)")
    render_process: bool = param(False, "4DGS: save progress renders while training",
                                 compat=True)
    add_points: bool = param(False, "add 100k random points inside the initial point cloud's "
                                    "bounding box", compat=True)
    extension: str = param(".png", "image file extension of Blender/D-NeRF datasets", compat=True)
    llffhold: int = param(8, "every llffhold-th frame is a test view (LLFF-style readers)",
                          check=_check_positive)
    # --- ours ---
    dataset_type: str = param("auto", "dataset reader (auto: chosen from the files present; synthetic: "
                                      "the simulator's scenes, NVIDIA layout, with their family config)",
                              ours=True, choices=DATASET_TYPES)
    force_dataset_points: bool = param(False, "start from the dataset's point file even when the "
                                              "training cameras barely see it (placeholder check)",
                                       ours=True)
    train_cameras: str = param("", "panoptic: rig camera ids the monocular protocol cycles over, one per "
                                   "timestamp, e.g. 21,29,24 (empty: the 5 training cameras nearest the "
                                   "first test camera)", ours=True)
    test_cameras: str = param("", "panoptic: test_meta.json camera ids held out with --eval, e.g. 0,10 "
                                  "(empty: the first test camera)", ours=True)
    test_every: int = param(10, "panoptic: with --eval the test cameras are test views at every "
                                "test_every-th timestamp", ours=True, check=_check_positive)


@dataclass
class PipelineParams:
    """Rendering pipeline switches (4DGS "Pipeline Parameters")."""

    convert_SHs_python: bool = param(False, "4DGS: evaluate SH colours in Python instead of the "
                                            "CUDA rasterizer (always done in torch here)",
                                     compat=True)
    compute_cov3D_python: bool = param(False, "4DGS: build 3D covariances in Python (always done "
                                              "in torch here)", compat=True)
    debug: bool = param(False, "4DGS: debug mode of its CUDA rasterizer (extra checks), from "
                               "--debug_from on", compat=True)
    # --- ours ---
    backend: str = param("auto", "rasterizer backend: auto (gsplat on CUDA, else cpu), cpu, "
                                 "reference (dense test oracle) or gsplat", ours=True,
                         choices=BACKENDS)
    device: str = param("auto", "compute device: auto (cuda when available), cpu, cuda, cuda:N",
                        ours=True, check=_check_device)
    time_outside: str = param("linear", "views at times outside the training views' span "
                              "(e.g. a held-out first frame): linear (the state at the nearest "
                              "trained time, centres moved on at their velocity there), hold (that "
                              "state as it is) or extrapolate (4DGS: evaluate the deformation there)",
                              ours=True, choices=("extrapolate", "hold", "linear"))


@dataclass
class ModelHiddenParams:
    """Deformation field: HexPlane grid and deformation MLP (4DGS "ModelHiddenParams")."""

    net_width: int = param(64, "width of the deformation MLP", check=_check_positive)
    timebase_pe: int = param(4, "4DGS: input encoding of a time network that 4DGS builds and never "
                                "calls; built here too, so its size changes only the random initial "
                                "weights drawn after it (as in 4DGS), not what is computed",
                             check=_check_non_negative)
    defor_depth: int = param(1, "number of hidden layers of the deformation MLP",
                             check=_check_non_negative)
    posebase_pe: int = param(10, "4DGS: position encoding whose result is discarded (" +
                             _COMPAT_4DGS_UNUSED + ")", compat=True)
    scale_rotation_pe: int = param(2, "4DGS: scale/rotation encoding whose result is discarded "
                                      "(" + _COMPAT_4DGS_UNUSED + ")", compat=True)
    opacity_pe: int = param(2, "4DGS: opacity encoding, unused (" + _COMPAT_4DGS_UNUSED + ")",
                            compat=True)
    timenet_width: int = param(64, "4DGS: width of the never-called time network (see timebase_pe: "
                                   "changes only the random initial weights drawn after it)",
                               check=_check_positive)
    timenet_output: int = param(32, "4DGS: output width of the never-called time network (see "
                                    "timebase_pe)", check=_check_positive)
    bounds: float = param(1.6, "initial half-extent of the HexPlane bounding box (reset from the "
                               "point cloud)")
    plane_tv_weight: float = param(0.0001, "total-variation loss weight of the spatial planes",
                                   check=_check_non_negative)
    time_smoothness_weight: float = param(0.01, "smoothness loss weight of the time planes; 0 also "
                                                "switches off plane_tv_weight and l1_time_planes (as "
                                                "in 4DGS, the three are one loss computed only then)",
                                          check=_check_non_negative)
    l1_time_planes: float = param(0.0001, "L1 loss weight pulling the time planes towards 1",
                                  check=_check_non_negative)
    kplanes_config: dict[str, Any] = param(
        {"grid_dimensions": 2, "input_coordinate_dim": 4, "output_coordinate_dim": 32,
         "resolution": [64, 64, 64, 25]},
        "HexPlane: grid_dimensions, input_coordinate_dim, output_coordinate_dim (feature "
        "channels), resolution [x, y, z, t] (t about half the number of frames)",
        check=_check_kplanes)
    multires: list[int] = param([1, 2, 4, 8], "spatial resolution multipliers of the HexPlane "
                                              "levels", check=_check_multires)
    mlp_precision: str = param("auto", "number format of the deformation MLP's matrix products: "
                                       "float32, bfloat16 (weights stay float32, autocast) or auto "
                                       "(bfloat16 on a CPU with native bfloat16 dot products, e.g. "
                                       "AMX or AVX512-BF16; float32 elsewhere)", ours=True,
                               choices=MLP_PRECISIONS)
    no_dx: bool = param(False, "disable the deformation of positions")
    no_grid: bool = param(False, "feed time and position to the MLP instead of HexPlane features")
    no_ds: bool = param(False, "disable the deformation of scales")
    no_dr: bool = param(False, "disable the deformation of rotations")
    no_do: bool = param(True, "disable the deformation of opacities")
    no_dshs: bool = param(True, "disable the deformation of SH colours")
    empty_voxel: bool = param(False, "4DGS experiment (labelled useless there): empty-space "
                                     "voxel mask; not supported (True is refused)",
                              check=_check_unsupported)
    grid_pe: int = param(0, "4DGS experiment (labelled useless there), implemented: 0 = off, k > 1 "
                            "= the grid features f followed by sin(k f) and cos(k f) as the MLP's "
                            "input", check=_check_grid_pe)
    static_mlp: bool = param(False, "4DGS experiment (labelled useless there): static/dynamic "
                                    "MLP mask; not supported (True is refused)", check=_check_unsupported)
    apply_rotation: bool = param(False, "4DGS experiment (labelled useless there), implemented: "
                                        "compose rotation deltas as quaternion products instead of "
                                        "adding them")


@dataclass
class OptimizationParams:
    """Optimisation schedule, learning rates, densification (4DGS "Optimization Parameters")."""

    dataloader: bool = param(False, "4DGS: load views through a torch DataLoader", compat=True)
    zerostamp_init: bool = param(False, "coarse stage uses only the views at time 0 (4DGS, for "
                                        "multi-view video)", compat=True)
    custom_sampler: str | None = param(None, "4DGS: custom DataLoader sampler", compat=True)
    iterations: int = param(30_000, "iterations of the fine stage (train.py needs >= 1: the fine model is "
                            "what a run saves)", check=_check_non_negative)
    coarse_iterations: int = param(3000, "iterations of the coarse (static) stage",
                                   check=_check_non_negative)
    position_lr_init: float = param(0.00016, "initial learning rate of positions "
                                             "(times the scene extent)", check=_check_non_negative)
    position_lr_final: float = param(0.0000016, "final learning rate of positions",
                                     check=_check_non_negative)
    position_lr_delay_mult: float = param(0.01, "4DGS: warm-up multiplier of the position learning "
                                                "rate; 4DGS sets no warm-up steps, so it has no effect "
                                                "there or here", compat=True)
    position_lr_max_steps: int = param(20_000, "steps of the position (and deformation) "
                                               "learning-rate decay", check=_check_positive)
    deformation_lr_init: float = param(0.00016, "initial learning rate of the deformation MLP",
                                       check=_check_non_negative)
    deformation_lr_final: float = param(0.000016, "final learning rate of the deformation MLP",
                                        check=_check_non_negative)
    deformation_lr_delay_mult: float = param(0.01, "4DGS: warm-up multiplier of the deformation "
                                                   "learning rate; no effect (see position_lr_delay_mult)",
                                             compat=True)
    grid_lr_init: float = param(0.0016, "initial learning rate of the HexPlane grid",
                                check=_check_non_negative)
    grid_lr_final: float = param(0.00016, "final learning rate of the HexPlane grid",
                                 check=_check_non_negative)
    feature_lr: float = param(0.0025, "learning rate of SH colours (rest: / 20)", check=_check_non_negative)
    opacity_lr: float = param(0.05, "learning rate of opacities", check=_check_non_negative)
    scaling_lr: float = param(0.005, "learning rate of scales", check=_check_non_negative)
    rotation_lr: float = param(0.001, "learning rate of rotations", check=_check_non_negative)
    percent_dense: float = param(0.01, "clone/split boundary, as a fraction of the scene extent",
                                 check=_check_non_negative)
    lambda_dssim: float = param(0.0, "weight of the (1 - SSIM) term of the photometric loss",
                                check=_check_non_negative)
    lambda_lpips: float = param(0.0, "4DGS: LPIPS loss weight (its code is commented out, " +
                                _COMPAT_4DGS_UNUSED + ")", compat=True)
    weight_constraint_init: float = param(1.0, "4DGS: unused (" + _COMPAT_4DGS_UNUSED + ")",
                                          compat=True)
    weight_constraint_after: float = param(0.2, "4DGS: unused (" + _COMPAT_4DGS_UNUSED + ")",
                                           compat=True)
    weight_decay_iteration: int = param(5000, "4DGS: unused (" + _COMPAT_4DGS_UNUSED + ")",
                                        compat=True)
    opacity_reset_interval: int = param(3000, "iterations between opacity resets",
                                        check=_check_positive)
    densification_interval: int = param(100, "iterations between densification steps",
                                        check=_check_positive)
    densify_from_iter: int = param(500, "densification from the iterations after this one (4DGS: iteration > it)")
    densify_until_iter: int = param(15_000, "densification (and its gradient statistics) up to the "
                                            "iteration before this one (4DGS: iteration < it)")
    densify_grad_threshold_coarse: float = param(0.0002, "view-space gradient threshold for "
                                                         "densification, coarse stage",
                                                 check=_check_non_negative)
    densify_grad_threshold_fine_init: float = param(0.0002, "same, fine stage, at its start",
                                                    check=_check_non_negative)
    densify_grad_threshold_after: float = param(0.0002, "same, fine stage, at densify_until_iter "
                                                        "(linear in between)", check=_check_non_negative)
    pruning_from_iter: int = param(500, "large-count pruning from the iterations after this one (4DGS: iteration > it)")
    pruning_interval: int = param(100, "iterations between large-count pruning steps",
                                  check=_check_positive)
    opacity_threshold_coarse: float = param(0.005, "opacity below which Gaussians are pruned, "
                                                   "coarse stage", check=_check_fraction)
    opacity_threshold_fine_init: float = param(0.005, "same, fine stage, at its start",
                                               check=_check_fraction)
    opacity_threshold_fine_after: float = param(0.005, "same, fine stage, at densify_until_iter",
                                                check=_check_fraction)
    batch_size: int = param(1, "views per iteration", check=_check_positive)
    add_point: bool = param(False, "grow points during densification (4DGS's gaussians.grow)", compat=True)
    # --- ours ---
    seed: int = param(0, "random seed (torch, numpy, python)", ours=True, check=_check_seed)
    densify_max_gaussians: int = param(360_000, "no densification above this many Gaussians "
                                       "(4DGS hard-codes 360000)", ours=True, check=_check_positive)
    prune_min_gaussians: int = param(200_000, "opacity pruning runs only above this many "
                                     "Gaussians (4DGS hard-codes 200000; small CPU scenes want 0)",
                                     ours=True, check=_check_non_negative)
    densify_grad_from: str = param("baseline", "which losses' screen-space gradients drive densification: "
                                   "baseline (the photometric reconstruction loss, 4DGS's statistic even "
                                   "when plugins add losses) or all", ours=True, choices=("baseline", "all"))
    stall_iterations: int = param(200, "stop a run that cannot learn (no Gaussian visible in any view, or a "
                                  "loss flat to 1e-4) after this many iterations from its start, with "
                                  "error: and exit 2 (0: never)", ours=True, check=_check_non_negative)
    nonfinite_skips: int = param(3, "a step whose gradients are NaN/inf is skipped (no densification statistic, "
                                 "no optimizer step), logged, and its starting state saved once to "
                                 "nonfinite_<stage>_<iteration>.pth for diagnosis; the run stops with error: "
                                 "after more than this many such steps in a row (0: at the first)",
                                 ours=True, check=_check_non_negative)


@dataclass
class RunParams:
    """Run-level flags of train.py (4DGS's train.py flags plus ours)."""

    ip: str = param("127.0.0.1", "4DGS: network GUI address (no GUI here)", compat=True)
    port: int = param(6009, "4DGS: network GUI port (no GUI here)", compat=True)
    debug_from: int = param(-1, "4DGS: iteration from which --debug is on (-1: never)", compat=True)
    detect_anomaly: bool = param(False, "torch.autograd anomaly detection")
    test_iterations: list[int] = param([3000, 7000, 14000], "iterations at which test views "
                                                            "are evaluated")
    save_iterations: list[int] = param([14000, 20000, 30_000, 45000, 60000],
                                       "iterations at which the model is saved (the last "
                                       "iteration is always saved)")
    quiet: bool = param(False, "less console output")
    checkpoint_iterations: list[int] = param([], "iterations at which a training checkpoint "
                                                 "(model + optimizer) is written")
    start_checkpoint: str | None = param(None, "checkpoint file or point_cloud/iteration_N "
                                               "directory to start from")
    expname: str = param("", "experiment name (model path output/<expname> when -m is not given)")
    configs: list[str] = param([], "config files, applied in order (command line only)")
    # --- ours ---
    plugin: list[str] = param([], "plugins to load by name (repeatable or comma list)",
                              ours=True, comma_list=True)
    disable: list[str] = param([], "plugin components to disable (comma list)", ours=True,
                               comma_list=True)
    enable: list[str] = param([], "plugin components to enable (comma list)", ours=True,
                              comma_list=True)
    log_every: int = param(10, "iterations between train_log.jsonl records (the console's progress line "
                           "refreshes every 10 iterations, or prints every 100 when not a terminal)", ours=True,
                           check=_check_positive)
    overwrite: bool = param(False, "clear the earlier run's files in -m before this run (without it, "
                            "a folder holding a run is refused)", ours=True)


@dataclass
class RenderParams:
    """Flags of the render command (4DGS's render.py)."""

    iteration: int = param(-1, "saved iteration to render (-1: the latest)",
                           check=_check_render_iteration)
    skip_train: bool = param(False, "do not render the training views")
    skip_test: bool = param(False, "do not render the test views")
    skip_video: bool = param(False, "do not render the video path")
    quiet: bool = param(False, "less console output: warnings and the written folders only")
    configs: list[str] = param([], "config files, applied over the saved configuration")


# Group names as they appear in config files, in 4DGS's order.
HOST_GROUPS: dict[str, type] = {
    "ModelParams": ModelParams,
    "PipelineParams": PipelineParams,
    "OptimizationParams": OptimizationParams,
    "ModelHiddenParams": ModelHiddenParams,
}
