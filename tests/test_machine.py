"""The machine record of a run (baselines/machine.py): what `auto` settings resolved to.

`--mlp_precision auto` computes the deformation MLP in bfloat16 on CPUs with native bfloat16 and
in float32 elsewhere, so the same command trains different models on two machines; run.json
must say which, and the autocast the MLP runs under must be the one recorded.
"""
from __future__ import annotations

import pytest
import torch

from baselines.fourdgs import deformation
from baselines.fourdgs.deformation import mlp_arithmetic, mlp_autocast
from baselines.machine import training_machine
from baselines.run_folder import read_run_record
from tests.test_run_folder import _train

CPU = torch.device("cpu")


@pytest.mark.parametrize("native", [True, False])
def test_auto_follows_the_cpu_and_the_explicit_values_do_not(monkeypatch, native):
    monkeypatch.setattr(deformation, "native_bfloat16_cpu", lambda: native)
    assert mlp_arithmetic("auto", CPU) == ("bfloat16" if native else "float32")
    assert mlp_arithmetic("float32", CPU) == "float32"
    assert mlp_arithmetic("bfloat16", CPU) == "bfloat16"
    assert mlp_arithmetic("auto", torch.device("cuda")) == "float32"  # auto is a CPU rule
    for precision in ("auto", "float32", "bfloat16"):  # the autocast agrees with what is recorded
        assert mlp_autocast(precision, CPU)._enabled == (mlp_arithmetic(precision, CPU) == "bfloat16")
        assert training_machine(CPU, "cpu", precision)["mlp_arithmetic"] == mlp_arithmetic(precision, CPU)


def test_an_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="mlp_precision must be auto, float32 or bfloat16, got 'half'"):
        mlp_arithmetic("half", CPU)


def test_the_record_names_the_resolved_backend_and_the_threads():
    record = training_machine(CPU, "auto", "float32")
    assert record["rasterizer"] == "cpu"  # auto on a CPU device
    assert record["device"] == "cpu" and record["threads"] == torch.get_num_threads()
    assert record["torch"] == torch.__version__ and record["cpu"]
    assert training_machine(CPU, "gsplat", "float32")["rasterizer"].startswith("unavailable: ")


def test_train_py_writes_the_machine_into_run_json(tiny_scene, tmp_path):
    run = tmp_path / "run"
    _train(tiny_scene, run, "--mlp_precision", "bfloat16")
    machine = read_run_record(run)["machine"]
    assert machine["mlp_arithmetic"] == "bfloat16" and machine["rasterizer"] == "cpu"
    assert machine["threads"] == torch.get_num_threads()
