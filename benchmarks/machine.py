"""What machine a benchmark ran on (printed with every table: the figures depend on it).

The functions live in baselines/machine.py (train.py records the same facts in run.json)."""
from __future__ import annotations

from baselines.machine import cpu_model, load_average

__all__ = ["cpu_model", "load_average"]
