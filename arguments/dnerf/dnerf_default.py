# D-NeRF (Blender) scenes: the values of 4DGS's arguments/dnerf/dnerf_default.py (hustvl/4DGaussians).
# 4DGS's file also sets render_process=False (the default) and weight_decay_iteration=0 (a field 4DGS
# never reads, placed under ModelHiddenParams); neither has an effect, so both are left out.
# Per-scene files (lego.py, ...) set the temporal resolution of the HexPlane.

OptimizationParams = dict(
    coarse_iterations=3000,
    deformation_lr_init=0.00016,
    deformation_lr_final=0.0000016,
    deformation_lr_delay_mult=0.01,
    grid_lr_init=0.0016,
    grid_lr_final=0.000016,
    iterations=20000,
    pruning_interval=8000,
    percent_dense=0.01,
)

ModelHiddenParams = dict(
    multires=[1, 2],
    defor_depth=0,
    net_width=64,
    plane_tv_weight=0.0001,
    time_smoothness_weight=0.01,
    l1_time_planes=0.0001,
    bounds=1.6,
)
