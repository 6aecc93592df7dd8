# D-NeRF "lego" (4DGS's arguments/dnerf/lego.py). Only the temporal resolution differs between the
# D-NeRF scenes: the dict below merges into the inherited kplanes_config key by key (grid_dimensions,
# input_coordinate_dim and output_coordinate_dim keep their values); write _delete_=True inside the
# dict to replace it as a whole instead.
_base_ = './dnerf_default.py'

ModelHiddenParams = dict(
    kplanes_config=dict(resolution=[64, 64, 64, 25]),
)
