"""What machine a benchmark ran on (printed with every table: the figures depend on it)."""
from __future__ import annotations

import os
import platform
from pathlib import Path


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
