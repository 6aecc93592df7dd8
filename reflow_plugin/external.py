"""External-flow supervision: the paper's "Ours (External Flow)" comparison (appendix, Table 6).

    cache = ExternalFlowCache(cache_dir)
    flow_ext, confident = cache.get(camera_a, camera_b)      # [H, W, 2] float, [H, W] bool tensors
    loss = external_flow_loss(rendered_flow, valid, flow_ext, confident)

The same model and pairs as ReFlow, but motion is supervised by an L1 loss between the rendered
full flow F_a->b and optical flow computed by OpenCV's DIS between the two ground-truth frames
(`baselines.data.optical_flow`), on pixels where the rendered flow is valid and the DIS flow passes
its forward-backward consistency test. DIS flows are computed once per ordered pair and cached
(`<cache_dir>/<a>__<b>.npz`, written atomically; a second run reads them).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from baselines.data import Camera
from baselines.data.optical_flow import consistent, flow_pair


class ExternalFlowCache:
    """DIS flow of ordered camera pairs, in memory and on disk."""

    def __init__(self, cache_dir: Path) -> None:
        self.cache_dir = Path(cache_dir)
        self._memory: dict[tuple[str, str], tuple[Tensor, Tensor]] = {}

    def _path(self, a: Camera, b: Camera) -> Path:
        return self.cache_dir / f"{a.image_name}__{b.image_name}.npz"

    def get(self, a: Camera, b: Camera) -> tuple[Tensor, Tensor]:
        """(flow a -> b [H, W, 2], confident [H, W] bool) on camera a's image device."""
        key = (a.image_name, b.image_name)
        if key not in self._memory:
            flow, ok = self._load_or_compute(a, b)
            device = a.image.device
            self._memory[key] = (torch.from_numpy(flow).to(device), torch.from_numpy(ok).to(device))
        return self._memory[key]

    def _load_or_compute(self, a: Camera, b: Camera) -> tuple[np.ndarray, np.ndarray]:
        path = self._path(a, b)
        if path.is_file():
            with np.load(path) as data:
                flow, ok = data["flow"], data["confident"]
            if flow.shape[:2] == (a.height, a.width):
                return flow.astype(np.float32), ok.astype(bool)
        image_a, image_b = a.image.detach().cpu().numpy(), b.image.detach().cpu().numpy()
        fwd, bwd = flow_pair(image_a, image_b)
        ok = consistent(fwd, bwd)
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        handle, tmp = tempfile.mkstemp(dir=self.cache_dir, suffix=".npz")
        os.close(handle)
        np.savez_compressed(tmp, flow=fwd.astype(np.float32), confident=ok)
        os.replace(tmp, path)
        return fwd.astype(np.float32), ok


def external_flow_loss(flow: Tensor, valid: Tensor, flow_ext: Tensor, confident: Tensor) -> Tensor:
    """Mean L1 (both components, pixels) of flow - flow_ext over valid & confident pixels.

    Args:
        flow: [H, W, 2] rendered full flow. valid: [H, W] bool. flow_ext: [H, W, 2]. confident: [H, W] bool.
    An empty mask gives a zero still connected to the graph.
    """
    mask = (valid & confident).to(flow.dtype).unsqueeze(-1)
    count = mask.sum()
    error = ((flow - flow_ext.to(flow.dtype)).abs() * mask).sum()
    return torch.where(count > 0, error / (2.0 * count.clamp_min(1.0)), flow.sum() * 0.0)
