# HyperNeRF "banana" (4DGS's arguments/hypernerf/banana.py, which puts kplanes_config under
# ModelParams; 4DGS flattens groups, so it lands in ModelHiddenParams as here).
_base_ = './default.py'

ModelHiddenParams = dict(
    kplanes_config=dict(resolution=[64, 64, 64, 250]),
)
