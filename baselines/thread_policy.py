"""OpenMP settings for shared machines, applied before torch starts (train.py, benchmarks).

By default OpenMP worker threads spin while they wait; on a busy 2-core machine (load 6-8) that
turned a 4-minute training job into 44 minutes wall and 32.5 minutes CPU. Before torch is
imported, and only for what the user did not set:

- ``OMP_WAIT_POLICY=PASSIVE``: waiting threads sleep instead of spinning;
- ``OMP_NUM_THREADS`` = the CPUs this process may run on (``os.sched_getaffinity``), when that is
  fewer than the machine's CPUs (a CPU set or container limit torch would otherwise ignore).

Nothing is changed once torch has been imported (its thread pool is then already configured).
"""
from __future__ import annotations

import os
import sys
from typing import MutableMapping


def available_cpus() -> int:
    """CPUs this process may run on (affinity mask where the platform has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def apply_thread_policy(environ: MutableMapping[str, str] | None = None,
                        torch_loaded: bool | None = None) -> dict[str, str]:
    """Set the policy's variables the user left unset in ``environ`` (default ``os.environ``).

    Returns the variables set (empty when torch was already imported or the user set them all).
    """
    environ = os.environ if environ is None else environ
    if torch_loaded is None:
        torch_loaded = "torch" in sys.modules
    if torch_loaded:
        return {}
    applied: dict[str, str] = {}
    if "OMP_WAIT_POLICY" not in environ:
        applied["OMP_WAIT_POLICY"] = "PASSIVE"
    cpus = available_cpus()
    if "OMP_NUM_THREADS" not in environ and cpus < (os.cpu_count() or cpus):
        applied["OMP_NUM_THREADS"] = str(cpus)
    environ.update(applied)
    return applied
