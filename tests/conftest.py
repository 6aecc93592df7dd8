"""Shared fixtures: small generated scenes (never committed binaries)."""
from __future__ import annotations

import os

# torch's OpenMP threads sleep instead of spinning while they wait: on a busy 2-core machine a
# spinning pool makes the rasterizer's many small tensor ops 10-50x slower. Must precede torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path  # noqa: E402

import pytest


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 32x32, 12-frame balloon scene from the simulator (NVIDIA layout; frames 0 and 8 held out)."""
    from baselines.synthetic import get_scene, simulate

    path = tmp_path_factory.mktemp("scenes") / "tiny_balloon"
    simulate(get_scene("balloon", frames=12, width=32, height=32, seed=0), path, progress=False)
    return path


@pytest.fixture(scope="session")
def tiny_reflow_run(tiny_scene, tmp_path_factory) -> Path:
    """A ReFlow run on `tiny_scene` trained for 10 + 30 iterations (separation with keyframe
    seeds, so a mixed deformation table and temporal windows; no comp_init: seconds, not minutes)."""
    from baselines.fourdgs.app import REPO_ROOT, build_trainer
    from tests.test_trainer import FAST

    out = tmp_path_factory.mktemp("runs") / "tiny_reflow"
    trainer = build_trainer(["-s", str(tiny_scene), "-m", str(out), "--configs",
                             str(REPO_ROOT / "arguments/synthetic/default.py"), "--coarse_iterations", "10",
                             "--iterations", "30", *FAST, "--plugin", "reflow", "--flow_vis_every", "0",
                             "--disable", "comp_init"])
    trainer.train()
    trainer.run_log.close()
    return out
