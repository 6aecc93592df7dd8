"""What a run or benchmark ran on: the figures depend on it.

    from baselines.machine import cpu_model, load_average, training_machine
    training_machine(device, backend="auto", mlp_precision="auto")
    # {"cpu": "AMD EPYC", "device": "cpu", "threads": 2, "torch": "2.13.0+cpu",
    #  "rasterizer": "cpu", "mlp_arithmetic": "float32"}

`train.py` stores `training_machine(...)` in the run's `run.json` under "machine" (the benchmarks
print it beside their tables). The one entry that changes a run's RESULTS, not only its speed, is
`mlp_arithmetic`: with `--mlp_precision auto` (the default) the deformation MLP computes in
bfloat16 on a CPU with native bfloat16 (AMX or AVX512-BF16) and in float32 elsewhere, so the same
command trains a slightly different model on two machines (baselines/fourdgs/deformation.py).
"""
from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch is imported late: the benchmarks import this before their thread policy
    import torch


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), else what platform knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def load_average(separator: str = " ") -> str:
    """1/5/15-minute load averages, e.g. '1.10 1.05 0.98' ('n/a' where unsupported)."""
    try:
        return separator.join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def training_machine(device: "torch.device", backend: str = "auto", mlp_precision: str = "auto") -> dict[str, Any]:
    """The facts of the machine a training runs on, with the choices `auto` settings resolved to:
    the rasterizer backend and the deformation MLP's arithmetic (both decided per machine)."""
    import torch

    from baselines.fourdgs.deformation import mlp_arithmetic
    from baselines.render.backends import resolve_backend

    record: dict[str, Any] = {"cpu": cpu_model(), "device": str(device), "threads": torch.get_num_threads(),
                              "torch": torch.__version__}
    if device.type == "cuda":
        record["gpu"] = torch.cuda.get_device_name(device)
    try:
        record["rasterizer"] = resolve_backend(backend, device).name
    except ValueError as error:  # reported where the renderer is first used; here only recorded
        record["rasterizer"] = f"unavailable: {error}"
    record["mlp_arithmetic"] = mlp_arithmetic(mlp_precision, device)
    return record
