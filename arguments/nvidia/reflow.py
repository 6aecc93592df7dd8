# ReFlow on top of this family's 4DGS config: python train.py -s DATA --plugin reflow --configs arguments/nvidia/reflow.py
# Weights for NVIDIA-like scenes (paper appendix A.4): lambda_ff 5.0, lambda_cf 0.3; lambda_cr = 0.1 x lambda_mc
# (cross_time_ratio). The other ReFlowParams keep their defaults (reflow_plugin/params.py).
_base_ = "./default.py"

ReFlowParams = dict(
    lambda_ff=5.0,
    lambda_cf=0.3,
    lambda_mc=1.0,
    cross_time_ratio=0.1,
)
