"""Training's memory measures change no result: the freed heap given back after a change of count,
and oneDNN's primitive caches capped (thread_policy.py; docs/PROFILE.md,
"Memory of a training run")."""
from __future__ import annotations

import subprocess
import sys

import torch

from baselines.fourdgs.app import REPO_ROOT, build_trainer
from tests.test_trainer import _final_params, base_argv


def _train(scene, out, monkeypatch, release) -> tuple[dict[str, torch.Tensor], list[float]]:
    """A short densifying run with ``release`` as the trainer's release_free_memory: (final
    parameters, loss of every step)."""
    monkeypatch.setattr("baselines.fourdgs.trainer.release_free_memory", release)
    trainer = build_trainer(base_argv(scene, out, 20, 40))
    losses: list[float] = []
    step = trainer.train_step

    def recorded() -> None:
        step()
        losses.append(float(trainer.ctx.loss.detach()))

    trainer.train_step = recorded
    trainer.train()
    return _final_params(trainer), losses


def test_giving_freed_memory_back_after_a_change_of_count_leaves_the_run_unchanged(tiny_scene, tmp_path, monkeypatch):
    from baselines.thread_policy import release_free_memory

    calls: list[int] = []

    def counted() -> bool:
        calls.append(1)
        return release_free_memory()

    released, released_losses = _train(tiny_scene, tmp_path / "released", monkeypatch, counted)
    kept, kept_losses = _train(tiny_scene, tmp_path / "kept", monkeypatch, lambda: False)
    assert calls, "the run must change its count (densify or prune) for the test to mean anything"
    assert released_losses == kept_losses
    assert released.keys() == kept.keys()
    for key in released:
        assert torch.equal(released[key], kept[key]), key


# A deformation-sized bfloat16 MLP, forward and backward over row counts that change as a
# densifying run's do; prints a digest of outputs and gradients.
_MLP_PROBE = """
import hashlib, torch
from baselines.fourdgs.deformation import mlp_autocast
torch.manual_seed(0)
net = torch.nn.Sequential(torch.nn.Linear(48, 128), torch.nn.ReLU(), torch.nn.Linear(128, 3))
digest = hashlib.sha256()
for rows in (3000, 3100, 3000, 3333, 3100):
    x = torch.randn(rows, 48, requires_grad=True)
    with mlp_autocast("bfloat16", torch.device("cpu")):
        y = net(x)
    y.float().square().sum().backward()
    for t in (y, x.grad, *(p.grad for p in net.parameters())):
        digest.update(t.detach().float().contiguous().numpy().tobytes())
    net.zero_grad(set_to_none=True)
print(digest.hexdigest())
"""


def test_a_small_primitive_cache_computes_the_same_bfloat16_mlp():
    """Capacity 1 rebuilds oneDNN's kernels at every shape change; they compute what cached ones do."""
    digests = []
    for entries in ("1", "1024"):
        env = {"ONEDNN_PRIMITIVE_CACHE_CAPACITY": entries, "LRU_CACHE_CAPACITY": entries, "OMP_NUM_THREADS": "1",
               "PATH": "/usr/bin:/bin"}
        out = subprocess.run([sys.executable, "-c", _MLP_PROBE], cwd=REPO_ROOT, env=env, capture_output=True,
                             text=True, check=True)
        digests.append(out.stdout.strip())
    assert digests[0] == digests[1]
