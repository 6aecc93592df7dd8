# HyperNeRF / Nerfies (vrig) scenes: the values of 4DGS's arguments/hypernerf/default.py
# (hustvl/4DGaussians). 4DGS's file also sets render_process=True (progress renders, which have no
# effect here), so it is left out. Per-scene files set the temporal resolution.

ModelHiddenParams = dict(
    kplanes_config=dict(
        grid_dimensions=2,
        input_coordinate_dim=4,
        output_coordinate_dim=16,
        resolution=[64, 64, 64, 150],
    ),
    multires=[1, 2, 4],
    defor_depth=1,
    net_width=128,
    plane_tv_weight=0.0002,
    time_smoothness_weight=0.001,
    l1_time_planes=0.0001,
)

OptimizationParams = dict(
    iterations=14_000,
    batch_size=2,
    coarse_iterations=3000,
    densify_until_iter=10_000,
    opacity_reset_interval=300_000,  # longer than the run: no opacity reset
)
