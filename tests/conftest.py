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
