"""The OpenMP policy of train.py and the benchmarks: applied only where the user set nothing."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from baselines import thread_policy
from baselines.fourdgs.app import REPO_ROOT


def test_policy_fills_only_what_the_user_left_unset(monkeypatch):
    monkeypatch.setattr(thread_policy, "available_cpus", lambda: 2)
    monkeypatch.setattr(thread_policy.os, "cpu_count", lambda: 8)  # a CPU set of 2 on an 8-CPU machine
    env: dict[str, str] = {}
    assert thread_policy.apply_thread_policy(env, torch_loaded=False) == {"OMP_WAIT_POLICY": "PASSIVE",
                                                                          "OMP_NUM_THREADS": "2"}
    assert env == {"OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "2"}
    user = {"OMP_WAIT_POLICY": "ACTIVE", "OMP_NUM_THREADS": "6"}
    assert thread_policy.apply_thread_policy(user, torch_loaded=False) == {}
    assert user == {"OMP_WAIT_POLICY": "ACTIVE", "OMP_NUM_THREADS": "6"}
    assert thread_policy.apply_thread_policy({}, torch_loaded=True) == {}  # too late: torch already set up


def test_thread_count_untouched_when_every_cpu_is_available(monkeypatch):
    monkeypatch.setattr(thread_policy, "available_cpus", lambda: 8)
    monkeypatch.setattr(thread_policy.os, "cpu_count", lambda: 8)
    assert thread_policy.apply_thread_policy({}, torch_loaded=False) == {"OMP_WAIT_POLICY": "PASSIVE"}


@pytest.mark.parametrize("user_policy", [None, "ACTIVE"])
def test_train_py_applies_the_policy_before_torch_unless_set(user_policy):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if user_policy:
        env["OMP_WAIT_POLICY"] = user_policy
    probe = ("import os, sys; import train; "
             "print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO_ROOT, env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == [user_policy or "PASSIVE", "True"]
