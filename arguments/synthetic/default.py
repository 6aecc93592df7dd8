# Generated scenes of baselines/synthetic (small images, a few dozen frames), sized to train on a
# laptop CPU in minutes. Not a 4DGS config: 4DGS's schedule scaled down about 5x so the stages and
# the densification window keep their proportions (coarse 10% of the fine stage, densification
# over the first two thirds), with a smaller HexPlane. Starting values, to be tuned.

ModelHiddenParams = dict(
    kplanes_config=dict(
        grid_dimensions=2,
        input_coordinate_dim=4,
        output_coordinate_dim=16,
        resolution=[32, 32, 32, 12],  # t: about half the frames (4DGS's rule of thumb)
    ),
    multires=[1, 2],
    defor_depth=0,
    net_width=64,
    plane_tv_weight=0.0002,
    time_smoothness_weight=0.001,
    l1_time_planes=0.0001,
)

OptimizationParams = dict(
    coarse_iterations=300,
    iterations=3000,
    position_lr_max_steps=3000,  # decay over the whole (short) run, as 20k does for 4DGS's 14-30k
    densify_from_iter=100,
    densify_until_iter=2000,
    densification_interval=50,
    pruning_from_iter=100,
    pruning_interval=50,
    opacity_reset_interval=100_000,  # longer than the run: no opacity reset
)

# Ours (4DGS config files have no RunParams): evaluate and save at points of the short schedule.
RunParams = dict(
    test_iterations=[1000, 3000],
    save_iterations=[3000],
)
