"""OpenMP and allocator settings for CPU training, applied before torch starts (train.py, benchmarks).

By default OpenMP worker threads spin while they wait; on a busy 2-core machine (load 6-8) that
turned a 4-minute training job into 44 minutes wall and 32.5 minutes CPU. Sleeping at once is
no cure either: a training step is some 3000 small ops, and waking a sleeping worker for each
parallel op made a fine iteration of the embedded scene 1.5x slower than a short spin. Before
torch is imported, and only for what the user did not set:

- ``OMP_WAIT_POLICY=PASSIVE`` with ``GOMP_SPINCOUNT=30000`` (libgomp, torch's OpenMP): a waiting
  thread spins for about 30k iterations (tens of microseconds, enough to catch the next op of a
  step) and then sleeps, so an idle or preempted pool does not burn a loaded machine's CPU;
- ``OMP_NUM_THREADS`` = the CPUs this process may run on (``os.sched_getaffinity``; a CPU set or
  container limit torch would otherwise ignore), lowered to the CPUs idle at start when other
  processes keep the machine busy (``/proc/stat`` sampled for 0.2 s; at least 1). On a 2-core
  machine with other jobs running, a 2-thread step waits at every parallel op for a worker that
  the scheduler has parked: a fine iteration measured 808 ms with 2 threads and 32 ms with 1
  (benchmarks/train_baseline.py under load). On a quiet machine every CPU is used;
- ``ONEDNN_PRIMITIVE_CACHE_CAPACITY`` and ``LRU_CACHE_CAPACITY`` (oneDNN's primitive cache and
  PyTorch's ideep cache above it) = ``PRIMITIVE_CACHE_ENTRIES`` instead of their default 1024.
  On a CPU with native bfloat16 the deformation MLP runs through oneDNN (``mlp_precision``), and
  oneDNN builds and caches a JIT-compiled kernel per matrix shape: a fine iteration uses 12 of
  them, and every densification or pruning changes the row count, so 12 more stay cached (about
  5 MiB a change). Besides that memory, the kernels are long-lived blocks created in the middle of
  a step's activations, where they split the freed heap into pieces the next, slightly larger
  activations no longer fit: a baseline training at 40k Gaussians had 4 GiB of freed but unusable
  heap after 300 iterations densifying every 5 (docs/PROFILE.md, "Memory of a training run").

Allocator (glibc only, any time, unless a ``MALLOC_*`` variable or ``GLIBC_TUNABLES`` is set):
glibc serves blocks above its mmap threshold (128 KiB, adapting up to 32 MiB) with fresh
``mmap``s, so every [N, 64] activation of a step page-faults again on first touch (2300 faults
per fine iteration of the embedded scene, about 11 us each on a VM), and a 4DGS-sized HexPlane
gradient (143 MB, 35k pages) costs 150 ms of faults per step. ``mallopt`` turns chunk ``mmap``s
off (``M_MMAP_MAX`` 0: every block comes from the heap and is reused once freed) and raises the
trim threshold to 512 MiB (freed memory at the heap's top is kept up to that much). The price:
up to 512 MiB of freed memory stays with the process, and memory freed below live blocks is
reused, not returned to the system. So the trainer calls ``release_free_memory`` (glibc's
``malloc_trim``: the pages of every free block go back) after a step that changed the number of
Gaussians: the activations of the new count are a little larger than the holes the old ones left,
so those holes would otherwise stay resident, unused, for the rest of the run.

Nothing about threads is changed once torch has been imported (its pool is then configured).
"""
from __future__ import annotations

import ctypes
import os
import platform
import sys
import time
from typing import MutableMapping

SPIN_COUNT = "30000"
# entries of oneDNN's and ideep's primitive caches: a training step uses 12 (a few times that
# with a plugin's extra networks), so the current row count's kernels stay cached
PRIMITIVE_CACHE_ENTRIES = "64"
PRIMITIVE_CACHE_VARIABLES = ("ONEDNN_PRIMITIVE_CACHE_CAPACITY", "LRU_CACHE_CAPACITY")
# glibc's mallopt parameters (malloc.h) and our values
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
TRIM_THRESHOLD_BYTES = 512 * 1024 * 1024
_MALLOC_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                     "GLIBC_TUNABLES")


def available_cpus() -> int:
    """CPUs this process may run on (affinity mask where the platform has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


# What the last apply_thread_policy on this process's environment decided, for the run's log.
last_decision = "no thread policy applied"


def idle_cpus(sample_seconds: float = 0.2, stat_path: str = "/proc/stat") -> float | None:
    """How many CPUs were idle over a short sample (``/proc/stat``), or None where unavailable.

    Idle = idle + iowait jiffies of the aggregate line; niced processes count as busy.
    """

    def read() -> tuple[int, int] | None:
        try:
            with open(stat_path) as handle:
                fields = handle.readline().split()
        except OSError:
            return None
        if not fields or fields[0] != "cpu" or len(fields) < 6:
            return None
        values = [int(v) for v in fields[1:]]
        return sum(values[:8]), values[3] + values[4]  # (total over user..steal, idle + iowait)

    first = read()
    if first is None:
        return None
    time.sleep(sample_seconds)
    second = read()
    if second is None or second[0] <= first[0]:
        return None
    share = (second[1] - first[1]) / (second[0] - first[0])
    return share * (os.cpu_count() or 1)


def thread_count(cpus: int, idle: float | None) -> int:
    """Threads for a process allowed ``cpus`` CPUs when ``idle`` CPUs are free (None: unknown)."""
    if idle is None:
        return cpus
    return max(1, min(cpus, int(idle + 0.5)))


def apply_thread_policy(environ: MutableMapping[str, str] | None = None,
                        torch_loaded: bool | None = None) -> dict[str, str]:
    """Set the policy's variables the user left unset in ``environ`` (default ``os.environ``).

    Returns the variables set (empty when torch was already imported or the user set them all).
    The allocator policy is applied too when ``environ`` is this process's environment.
    """
    own_process = environ is None
    environ = os.environ if environ is None else environ
    if own_process:
        apply_allocator_policy(environ)
    if torch_loaded is None:
        torch_loaded = "torch" in sys.modules
    if torch_loaded:
        return {}
    applied: dict[str, str] = {}
    if "OMP_WAIT_POLICY" not in environ:
        applied["OMP_WAIT_POLICY"] = "PASSIVE"
        if "GOMP_SPINCOUNT" not in environ:
            applied["GOMP_SPINCOUNT"] = SPIN_COUNT
    for name in PRIMITIVE_CACHE_VARIABLES:
        if name not in environ:
            applied[name] = PRIMITIVE_CACHE_ENTRIES
    decision = f"OMP_NUM_THREADS={environ['OMP_NUM_THREADS']} (yours)" if "OMP_NUM_THREADS" in environ else ""
    if "OMP_NUM_THREADS" not in environ:
        cpus = available_cpus()
        idle = idle_cpus() if cpus > 1 else None
        threads = thread_count(cpus, idle)
        if threads < (os.cpu_count() or cpus):
            applied["OMP_NUM_THREADS"] = str(threads)
        busy = f"; {idle:.1f} CPUs idle at start: the machine is busy" if threads < cpus else ""
        decision = f"{threads} threads ({cpus} CPUs available{busy}; set OMP_NUM_THREADS to choose)"
    environ.update(applied)
    if own_process:
        global last_decision
        last_decision = decision
    return applied


def _glibc() -> object | None:
    """The process's C library when it is glibc on Linux (its malloc tunables exist), else None."""
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL(None)
    except OSError:
        return None


def apply_allocator_policy(environ: MutableMapping[str, str] | None = None, libc: object | None = None) -> bool:
    """No chunk mmaps and a high trim threshold in glibc (see the module docstring); True when applied.

    Skipped off glibc and when the user tuned malloc through the environment. ``libc`` is for tests.
    """
    environ = os.environ if environ is None else environ
    if any(name in environ for name in _MALLOC_VARIABLES):
        return False
    libc = libc if libc is not None else _glibc()
    mallopt = getattr(libc, "mallopt", None)
    if mallopt is None:
        return False
    # mallopt returns 1 on success
    return bool(mallopt(M_MMAP_MAX, 0)) & bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))


def release_free_memory(libc: object | None = None) -> bool:
    """Give the pages of glibc's free heap blocks back to the system (``malloc_trim(0)``).

    What the allocator kept for reuse is released; live memory is untouched, so results do not
    change, and a later step that reuses a released page faults it in again. True when glibc
    released something; False off glibc. ``libc`` is for tests.
    """
    libc = libc if libc is not None else _glibc()
    trim = getattr(libc, "malloc_trim", None)
    return bool(trim(0)) if trim is not None else False
