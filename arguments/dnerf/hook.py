# D-NeRF "hook" (4DGS's arguments/dnerf/hook.py); see lego.py for how the dict merges.
_base_ = './dnerf_default.py'

ModelHiddenParams = dict(
    kplanes_config=dict(resolution=[64, 64, 64, 50]),
)
