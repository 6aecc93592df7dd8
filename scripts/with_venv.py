#!/usr/bin/env python3
"""Run a command inside the project's own virtual environment, creating it first if needed.

    python3 scripts/with_venv.py train.py              # the main job (embedded synthetic scene)
    python3 scripts/with_venv.py -m pytest -q          # the test suite

Everything after the script name is handed to the environment's Python unchanged.

The environment lives in ``<repo>/.venv``. It is (re)built when it is missing or when the install
recipe changed (``setup.cfg`` or the pins below), and reused otherwise, so the second call starts at
once. torch is installed first and pinned (``FOURDGS_TORCH``, default ``torch==2.13.0``, a CPU wheel
on our machines) so that no later requirement can pull a multi-GB CUDA build from the registry.
Optional extras (``cuda`` for gsplat, ``lpips``) are added with ``FOURDGS_EXTRAS=cuda,lpips``.
Only the standard library is used here: a fresh machine has nothing else.
"""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
VENV_DIR = Path(os.environ.get("FOURDGS_VENV", REPO / ".venv"))
TORCH_SPEC = os.environ.get("FOURDGS_TORCH", "torch==2.13.0")
EXTRAS = ["test"] + [e for e in os.environ.get("FOURDGS_EXTRAS", "").split(",") if e.strip()]
STAMP = VENV_DIR / ".fourdgs-install-stamp"


def venv_python() -> Path:
    """Path of the interpreter inside the environment."""
    if os.name == "nt":
        return VENV_DIR / "Scripts" / "python.exe"
    return VENV_DIR / "bin" / "python"


def recipe_digest() -> str:
    """Hash of everything that decides what gets installed."""
    h = hashlib.sha256()
    h.update((REPO / "setup.cfg").read_bytes())
    h.update(TORCH_SPEC.encode())
    h.update(",".join(sorted(EXTRAS)).encode())
    h.update(sys.version.encode())
    return h.hexdigest()


def pip(*args: str) -> None:
    """Run pip inside the environment, failing loudly with the command that broke."""
    cmd = [str(venv_python()), "-m", "pip", "--disable-pip-version-check", "install", *args]
    print(f"[venv] {' '.join(cmd[3:])}", flush=True)
    result = subprocess.run(cmd, cwd=REPO)
    if result.returncode != 0:
        sys.exit(f"[venv] installation failed: {' '.join(cmd)} (exit code {result.returncode})")


def ensure_environment() -> None:
    """Create the environment and install the project into it unless it is up to date."""
    digest = recipe_digest()
    if venv_python().exists() and STAMP.exists() and STAMP.read_text().strip() == digest:
        return
    if not venv_python().exists():
        print(f"[venv] creating {VENV_DIR}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV_DIR)
    pip("-q", TORCH_SPEC)
    pip("-q", "-e", f".[{','.join(EXTRAS)}]")
    STAMP.write_text(digest + "\n")


def main() -> None:
    ensure_environment()
    python = str(venv_python())
    args = [python, *sys.argv[1:]]
    if os.name == "nt":  # execv does not replace the process on Windows; keep the exit code.
        sys.exit(subprocess.run(args).returncode)
    os.execv(python, args)


if __name__ == "__main__":
    main()
