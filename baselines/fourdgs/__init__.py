"""4DGS baseline: Gaussian model, HexPlane deformation, trainer loop, hooks, plugins, checkpoints."""

from baselines.fourdgs.checkpoint import (
    TrainingState,
    atomic_save,
    atomic_write_ply,
    find_latest_iteration,
    load_point_cloud_dir,
    load_training_state,
    point_cloud_dir,
    read_gaussian_ply,
    save_point_cloud_dir,
    save_training_state,
    training_state_path,
)
from baselines.fourdgs.deformation import (
    Deformation,
    DeformationModule,
    DeformNetwork,
    check_deformation_state,
    deform_network,
    load_deformation_state,
)
from baselines.fourdgs.densification import DensificationRecord, densification_step, densification_thresholds
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.hexplane import HexPlaneField
from baselines.fourdgs.lr_schedule import get_expon_lr_func
from baselines.fourdgs.state import GaussianState

__all__ = [
    "Deformation",
    "DeformationModule",
    "DeformNetwork",
    "DensificationRecord",
    "GaussianModel",
    "GaussianState",
    "HexPlaneField",
    "TrainingState",
    "atomic_save",
    "atomic_write_ply",
    "check_deformation_state",
    "deform_network",
    "densification_step",
    "densification_thresholds",
    "find_latest_iteration",
    "get_expon_lr_func",
    "load_deformation_state",
    "load_point_cloud_dir",
    "load_training_state",
    "point_cloud_dir",
    "read_gaussian_ply",
    "save_point_cloud_dir",
    "save_training_state",
    "training_state_path",
]
