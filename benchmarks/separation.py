"""Cost of the separated deformation versus the share of dynamic Gaussians, in one run.

    python benchmarks/separation.py [--gaussians 20000] [--repeats 9]

Forward + backward of the deformation alone (synthetic config's HexPlane), median of interleaved
repeats: 4DGS's `DeformNetwork` on every Gaussian, then `SeparatedDeformation` with 0%, 20%, 50%
and 100% dynamic Gaussians, without and with keyframe anchoring (the anchored field is evaluated
twice per dynamic Gaussian: at t - t_k and at 0), and 20% dynamic in 8 keyframe windows (ReFlow's
initial widths) at t = 0.5 without and with `window_cull` (only the copies alive at t deformed).
Prints a table; asserts nothing.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()  # before torch: OpenMP waits, threads, allocator (baselines/thread_policy.py)

import torch  # noqa: E402

import types  # noqa: E402

from arguments.config import read_config_chain  # noqa: E402
from baselines.fourdgs.deformation import DeformNetwork  # noqa: E402
from baselines.fourdgs.state import GaussianState  # noqa: E402
from reflow_plugin.separation import TIME_CENTER, TIME_LOG_SCALE, SeparatedDeformation  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "arguments" / "synthetic" / "default.py"


def hidden_params() -> types.SimpleNamespace:
    """The config's ModelHiddenParams (missing fields take 4DGS's defaults in DeformNetwork)."""
    values: dict = {}
    for _, raw in read_config_chain(CONFIG):
        values.update(raw.get("ModelHiddenParams", {}))
    return types.SimpleNamespace(**values)


def time_call(module, state: GaussianState, times, buffers) -> float:
    start = time.perf_counter()
    out = module(state, times, buffers)
    (out.means.sum() + out.log_scales.sum() + out.rotations.sum()).backward()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    torch.manual_seed(0)
    n = args.gaussians
    hidden = hidden_params()
    baseline = DeformNetwork(hidden)
    separated = SeparatedDeformation(hidden, zero_init=False)
    culled = SeparatedDeformation(hidden, zero_init=False, window_cull=1e-3)
    culled.load_state_dict(separated.state_dict())
    for module in (baseline, separated, culled):
        module.set_aabb(torch.ones(3), -torch.ones(3))

    def make_state() -> GaussianState:
        return GaussianState(torch.rand(n, 3) * 2 - 1, torch.randn(n, 3).requires_grad_(), torch.randn(n, 4),
                             torch.randn(n, 1), torch.randn(n, 16, 3))

    times = torch.full((n, 1), 0.5)
    centers = torch.rand(n, 1)
    cases = {"4DGS DeformNetwork (all)": (baseline, None)}
    for share in (0.0, 0.2, 0.5, 1.0):
        table = torch.zeros(n, dtype=torch.bool)
        table[: int(share * n)] = True
        cases[f"separated, {share:.0%} dynamic"] = (separated, {"deformation_table": table})
        if share > 0:
            cases[f"separated, {share:.0%} dynamic, anchored keyframes"] = (
                separated, {"deformation_table": table, TIME_CENTER: centers})
    # 8 keyframe copies with ReFlow's initial windows (0.6 x the keyframe spacing), 20% dynamic
    table = torch.zeros(n, dtype=torch.bool)
    table[: n // 5] = True
    keyframe_times = torch.linspace(0, 1, 8)
    windows = {"deformation_table": table, TIME_CENTER: keyframe_times[torch.randint(8, (n, 1))],
               TIME_LOG_SCALE: torch.full((n, 1), math.log(0.6 / 7))}
    cases["separated, 20% dynamic, anchored, 8 keyframe windows"] = (separated, windows)
    cases["separated, 20% dynamic, anchored, 8 keyframe windows, window_cull 1e-3"] = (culled, windows)
    samples = {name: [] for name in cases}
    for _ in range(args.repeats):
        for name, (module, buffers) in cases.items():
            module.zero_grad(set_to_none=True)
            samples[name].append(time_call(module, make_state(), times, buffers))
    base = statistics.median(samples["4DGS DeformNetwork (all)"])
    print(f"# {n} Gaussians, synthetic config HexPlane, fwd+bwd, median of {args.repeats}; "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads, load average {os.getloadavg()[0]:.2f}")
    print("| case | ms | vs 4DGS |")
    print("|---|---:|---:|")
    for name, values in samples.items():
        median = statistics.median(values)
        print(f"| {name} | {1000 * median:.1f} | {median / base:.2f}x |")


if __name__ == "__main__":
    main()
