"""Shared fixtures: small generated scenes (never committed binaries)."""
from __future__ import annotations

import os

# torch's OpenMP threads sleep instead of spinning while they wait: on a busy 2-core machine a
# spinning pool makes the rasterizer's many small tensor ops 10-50x slower. Must precede torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# pytest-xdist workers share the CPUs: each gets its share of threads (at least 1), else every
# worker's pool would claim all of them and the workers would wait on one another's threads.
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):
    _cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, _cpus // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))))

import json  # noqa: E402
import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 32x32, 12-frame balloon scene from the simulator (NVIDIA layout; frames 0 and 8 held out)."""
    from baselines.synthetic import get_scene, simulate

    path = tmp_path_factory.mktemp("scenes") / "tiny_balloon"
    simulate(get_scene("balloon", frames=12, width=32, height=32, seed=0), path, progress=False)
    return path


def _depth_points(scene: Path, frames: list[int]) -> np.ndarray:
    """[P, 6] xyz + rgb (0-255): the simulator's depth of some frames back-projected with its cameras."""
    import cv2

    meta = json.loads((scene / "gt" / "cameras.json").read_text())["frames"]
    rows = []
    for f in frames:
        depth = np.load(scene / "gt" / "depth" / f"{f:03d}.npy")
        rgb = cv2.cvtColor(cv2.imread(str(scene / "images" / f"{f:03d}.png")), cv2.COLOR_BGR2RGB)
        h, w = depth.shape
        j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        rays = np.stack([j, i, np.ones_like(j)], -1) @ np.linalg.inv(np.array(meta[f]["K"])).T
        cam = rays * depth[..., None]
        c2w = np.linalg.inv(np.array(meta[f]["viewmat"]))
        world = cam.reshape(-1, 3) @ c2w[:3, :3].T + c2w[:3, 3]
        keep = np.isfinite(depth.ravel())
        rows.append(np.concatenate([world[keep], rgb.reshape(-1, 3)[keep]], 1))
    return np.concatenate(rows).astype(np.float32)


@pytest.fixture(scope="session")
def tiny_reflow_run(tiny_scene, tmp_path_factory) -> Path:
    """A ReFlow run trained for 10 + 30 iterations on a copy of `tiny_scene` given a point file
    (the simulator's depth of two frames, so the model shows the scene from the start: 32x32
    frames triangulate nothing). Separation with keyframe seeds, so a mixed deformation table and
    temporal windows; no comp_init: seconds, not minutes."""
    from baselines.fourdgs.app import REPO_ROOT, build_trainer
    from tests.test_trainer import FAST

    scene = tmp_path_factory.mktemp("scenes") / "tiny_balloon_points"
    shutil.copytree(tiny_scene, scene)
    np.save(scene / "points.npy", _depth_points(scene, [1, 6]))
    out = tmp_path_factory.mktemp("runs") / "tiny_reflow"
    trainer = build_trainer(["-s", str(scene), "-m", str(out), "--configs",
                             str(REPO_ROOT / "arguments/synthetic/default.py"), "--coarse_iterations", "10",
                             "--iterations", "30", *FAST, "--plugin", "reflow", "--flow_vis_every", "0",
                             "--disable", "comp_init"])
    trainer.train()
    trainer.run_log.close()
    return out
