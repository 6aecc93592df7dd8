"""Reuse of finished stages: each stage is keyed by a digest of its inputs and options.

    cache = StageCache(work_dir)
    key = cache.key("features", previous_key, options)
    if not cache.done("features", key):
        ...run it...
        cache.finish("features", key, extra={...})

The state lives in `work_dir/state.json`. A stage whose key changed is re-run, and so is every
stage after it (their keys include the previous stage's key). A source file is identified by its
absolute path, size and modification time (not its content: videos are large).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

STATE_FILE = "state.json"


def file_identity(path: Path) -> dict:
    """Absolute path, size and mtime of a file, or of every file of a folder."""
    path = Path(path).resolve()
    if path.is_dir():
        return {"folder": str(path), "files": [file_identity(p) for p in sorted(path.iterdir()) if p.is_file()]}
    stat = path.stat()
    return {"file": str(path), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}


class StageCache:
    """Keys and completion records of the prepare stages in one work folder."""

    def __init__(self, work_dir: Path):
        self.work_dir = Path(work_dir)
        self.path = self.work_dir / STATE_FILE
        try:
            self.state: dict[str, Any] = json.loads(self.path.read_text())
        except (OSError, ValueError):
            self.state = {}
        self.reused: list[str] = []

    @staticmethod
    def key(*parts: Any) -> str:
        """Digest of JSON-serialisable parts."""
        return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]

    def done(self, stage: str, key: str) -> bool:
        """True (and recorded as reused) when `stage` finished with this key."""
        record = self.state.get(stage)
        hit = isinstance(record, dict) and record.get("key") == key
        if hit:
            self.reused.append(stage)
        return hit

    def extra(self, stage: str) -> dict:
        """What `finish` stored with the stage."""
        return dict(self.state.get(stage, {}).get("extra", {}))

    def finish(self, stage: str, key: str, extra: dict | None = None) -> None:
        """Record `stage` as finished with `key` (written atomically)."""
        self.state[stage] = {"key": key, "extra": extra or {}}
        self.work_dir.mkdir(parents=True, exist_ok=True)
        temp = self.path.with_suffix(".tmp")
        temp.write_text(json.dumps(self.state, indent=1))
        os.replace(temp, self.path)
