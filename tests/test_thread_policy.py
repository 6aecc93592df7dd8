"""The OpenMP policy of train.py and the benchmarks: applied only where the user set nothing."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from baselines import thread_policy
from baselines.fourdgs.app import REPO_ROOT

# oneDNN's and ideep's primitive caches, capped unless the user set them
CACHES = {name: thread_policy.PRIMITIVE_CACHE_ENTRIES for name in thread_policy.PRIMITIVE_CACHE_VARIABLES}


def test_policy_fills_only_what_the_user_left_unset(monkeypatch):
    monkeypatch.setattr(thread_policy, "available_cpus", lambda: 2)
    monkeypatch.setattr(thread_policy, "idle_cpus", lambda: 8.0)
    monkeypatch.setattr(thread_policy.os, "cpu_count", lambda: 8)  # a CPU set of 2 on an 8-CPU machine
    env: dict[str, str] = {}
    expected = {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": thread_policy.SPIN_COUNT, **CACHES,
                "OMP_NUM_THREADS": "2"}
    assert thread_policy.apply_thread_policy(env, torch_loaded=False) == expected
    assert env == expected
    user = {"OMP_WAIT_POLICY": "ACTIVE", "OMP_NUM_THREADS": "6", "ONEDNN_PRIMITIVE_CACHE_CAPACITY": "1024",
            "LRU_CACHE_CAPACITY": "8"}
    kept = dict(user)
    assert thread_policy.apply_thread_policy(user, torch_loaded=False) == {}
    assert user == kept
    assert thread_policy.apply_thread_policy({}, torch_loaded=True) == {}  # too late: torch already set up


def test_thread_count_untouched_when_every_cpu_is_available(monkeypatch):
    monkeypatch.setattr(thread_policy, "available_cpus", lambda: 8)
    monkeypatch.setattr(thread_policy, "idle_cpus", lambda: 7.8)
    monkeypatch.setattr(thread_policy.os, "cpu_count", lambda: 8)
    assert thread_policy.apply_thread_policy({}, torch_loaded=False) == {"OMP_WAIT_POLICY": "PASSIVE",
                                                                         "GOMP_SPINCOUNT": thread_policy.SPIN_COUNT,
                                                                         **CACHES}


def test_a_busy_machine_gets_fewer_threads(monkeypatch):
    monkeypatch.setattr(thread_policy, "available_cpus", lambda: 2)
    monkeypatch.setattr(thread_policy.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(thread_policy, "idle_cpus", lambda: 0.3)
    assert thread_policy.apply_thread_policy({}, torch_loaded=False)["OMP_NUM_THREADS"] == "1"
    monkeypatch.setattr(thread_policy, "idle_cpus", lambda: 1.9)  # quiet: every CPU, nothing to set
    assert "OMP_NUM_THREADS" not in thread_policy.apply_thread_policy({}, torch_loaded=False)
    user = {"OMP_NUM_THREADS": "2"}
    monkeypatch.setattr(thread_policy, "idle_cpus", lambda: 0.0)
    thread_policy.apply_thread_policy(user, torch_loaded=False)
    assert user["OMP_NUM_THREADS"] == "2"  # the user's choice wins


@pytest.mark.parametrize("cpus, idle, expected", [(2, None, 2), (2, 0.0, 1), (2, 0.6, 1), (2, 1.5, 2), (8, 3.4, 3),
                                                  (4, 9.0, 4)])
def test_thread_count_follows_the_idle_cpus(cpus, idle, expected):
    assert thread_policy.thread_count(cpus, idle) == expected


def test_idle_cpus_reads_the_aggregate_line_of_proc_stat(tmp_path, monkeypatch):
    stat = tmp_path / "stat"
    # user nice system idle iowait irq softirq steal: 400 jiffies pass, 100 of them idle or iowait
    stat.write_text("cpu  1000 0 500 2000 100 0 0 0 0 0\ncpu0 1 2 3 4 5 6 7 8\n")
    monkeypatch.setattr(thread_policy.time, "sleep",
                        lambda s: stat.write_text("cpu  1250 20 530 2090 110 0 0 0 0 0\n"))
    monkeypatch.setattr(thread_policy.os, "cpu_count", lambda: 4)
    assert thread_policy.idle_cpus(stat_path=str(stat)) == pytest.approx(4 * 100 / 400)
    assert thread_policy.idle_cpus(stat_path=str(tmp_path / "missing")) is None


def test_a_user_spin_count_is_kept():
    env = {"GOMP_SPINCOUNT": "0", "OMP_NUM_THREADS": "2"}
    assert thread_policy.apply_thread_policy(env, torch_loaded=False) == {"OMP_WAIT_POLICY": "PASSIVE", **CACHES}
    assert env["GOMP_SPINCOUNT"] == "0"


class _FakeLibc:
    def __init__(self, result: int = 1) -> None:
        self.calls: list[tuple[int, int]] = []
        self.result = result

    def mallopt(self, param: int, value: int) -> int:
        self.calls.append((param, value))
        return self.result

    def malloc_trim(self, pad: int) -> int:
        self.calls.append(("malloc_trim", pad))
        return self.result


def test_allocator_policy_turns_chunk_mmaps_off_and_raises_the_trim_threshold():
    libc = _FakeLibc()
    assert thread_policy.apply_allocator_policy({}, libc=libc)
    assert libc.calls == [(thread_policy.M_MMAP_MAX, 0),
                          (thread_policy.M_TRIM_THRESHOLD, thread_policy.TRIM_THRESHOLD_BYTES)]
    assert not thread_policy.apply_allocator_policy({}, libc=_FakeLibc(result=0))  # glibc refused


@pytest.mark.parametrize("variable", ["MALLOC_MMAP_THRESHOLD_", "GLIBC_TUNABLES"])
def test_allocator_policy_leaves_a_tuned_malloc_alone(variable):
    libc = _FakeLibc()
    assert not thread_policy.apply_allocator_policy({variable: "1"}, libc=libc)
    assert libc.calls == []


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="glibc only")
def test_allocator_policy_is_accepted_by_the_real_glibc():
    """glibc accepts our values (it rejects out-of-range ones with 0)."""
    code = "from baselines import thread_policy as t; print(t.apply_allocator_policy({}))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True"]


def test_release_free_memory_trims_the_whole_heap():
    libc = _FakeLibc()
    assert thread_policy.release_free_memory(libc=libc)
    assert libc.calls == [("malloc_trim", 0)]  # pad 0: every free page above and below live blocks
    assert not thread_policy.release_free_memory(libc=object())  # no malloc_trim: nothing done


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="glibc only")
def test_release_free_memory_returns_freed_pages_with_the_real_glibc():
    """Freed heap blocks under the policy (no chunk mmaps) stay resident until released."""
    code = ("import ctypes, re; from baselines import thread_policy as t; t.apply_allocator_policy({}); "
            "rss = lambda: int(re.search(r'VmRSS:\\s+(\\d+)', open('/proc/self/status').read()).group(1)); "
            "blocks = [ctypes.create_string_buffer(4 << 20) for _ in range(32)]; "
            "live = ctypes.create_string_buffer(64); del blocks; before = rss(); "
            "print(t.release_free_memory(), before - rss() > 64 << 10)")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True"]  # more than 64 MiB of the 128 MiB freed went back


@pytest.mark.parametrize("user_policy", [None, "ACTIVE"])
def test_train_py_applies_the_policy_before_torch_unless_set(user_policy):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if user_policy:
        env["OMP_WAIT_POLICY"] = user_policy
    # train.py imports torch only in main(), after its model-folder check: the policy comes first
    probe = ("import os, sys; import train; torch_at_import = 'torch' in sys.modules; "
             "import baselines.fourdgs.app; "
             "print(os.environ.get('OMP_WAIT_POLICY'), torch_at_import, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO_ROOT, env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == [user_policy or "PASSIVE", "False", "True"]
