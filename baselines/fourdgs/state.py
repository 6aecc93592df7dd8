"""Per-Gaussian state passed between the model, the deformation module and the renderer.

Values are stored pre-activation, exactly as 4DGS stores them (log-scales, opacity logits,
unnormalised w,x,y,z quaternions, SH coefficients with the DC term first), so a state built
from a 4DGS checkpoint needs no conversion. The activated views the rasterizer wants are
properties computed on access.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

STATE_FIELDS = ("means", "log_scales", "rotations", "opacity_logits", "shs")  # GaussianState's field order
_FIELDS = STATE_FIELDS
# Largest log-scale the activation passes on (ours; 4DGS has no bound). A deformation network that
# runs away for one Gaussian can add +40..+100 to its log-scale (seen on DAVIS motocross-jump:
# +97 at one time, exp() = inf in float32, and the run died at fine iteration 715). exp(20) = 4.9e8
# scene units is larger than any real Gaussian yet keeps s^2 and the projected covariances finite;
# a clamped axis gets no gradient, its Gaussian's opacity and colour still do.
MAX_LOG_SCALE = 20.0


def activate_log_scales(log_scales: Tensor) -> Tensor:
    """[..., 3] log-scales -> standard deviations exp(min(log_scale, MAX_LOG_SCALE)), always finite
    for finite input."""
    return torch.exp(log_scales.clamp(max=MAX_LOG_SCALE))


def stand_in(like: Tensor, rows: int) -> Tensor:
    """[rows, *like.shape[1:]] zeros of like's dtype and device that take no memory (one value
    broadcast) and carry no gradient: a field a callee must pass through without reading it.
    Whoever hands one over checks that it came back as the same object, so it never reaches a
    render or a loss (`GaussianModel.deform_many`, reflow_plugin.separation)."""
    return like.new_zeros(()).expand(rows, *like.shape[1:])


@dataclass(frozen=True)
class GaussianState:
    """N Gaussians, pre-activation.

    Attributes:
        means: [N, 3] centres.
        log_scales: [N, 3] log of the per-axis standard deviations.
        rotations: [N, 4] unnormalised quaternions, w first.
        opacity_logits: [N, 1] inverse-sigmoid opacities.
        shs: [N, K, 3] SH coefficients, K = (degree + 1)^2, DC first.
    """

    means: Tensor
    log_scales: Tensor
    rotations: Tensor
    opacity_logits: Tensor
    shs: Tensor

    # ----------------------------------------------------------------------------------------
    # Activated views (what the rasterizer consumes).
    @property
    def scales(self) -> Tensor:
        """[N, 3] standard deviations (exp of the stored log-scales, capped: `activate_log_scales`)."""
        return activate_log_scales(self.log_scales)

    @property
    def quats(self) -> Tensor:
        """[N, 4] unit quaternions (w, x, y, z)."""
        return F.normalize(self.rotations, dim=-1)

    @property
    def opacities(self) -> Tensor:
        """[N] opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits).squeeze(-1)

    # ----------------------------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def sh_degree(self) -> int:
        """Largest SH degree the stored coefficients can represent."""
        return int(round(self.shs.shape[1] ** 0.5)) - 1

    @property
    def device(self) -> torch.device:
        return self.means.device

    def validate(self) -> GaussianState:
        """Raise ``ValueError`` naming the first field whose shape breaks the contract."""
        n = self.means.shape[0] if self.means.dim() > 0 else -1
        expected = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "rotations": (n, 4),
            "opacity_logits": (n, 1),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor) or tuple(value.shape) != shape:
                got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise ValueError(f"GaussianState.{name}: expected shape {list(shape)}, got {got}")
        shs = self.shs
        if not isinstance(shs, Tensor) or shs.dim() != 3 or shs.shape[0] != n or shs.shape[2] != 3:
            got = tuple(shs.shape) if isinstance(shs, Tensor) else type(shs).__name__
            raise ValueError(f"GaussianState.shs: expected shape [{n}, K, 3], got {got}")
        k = shs.shape[1]
        if int(round(k**0.5)) ** 2 != k:
            raise ValueError(f"GaussianState.shs: K={k} is not (degree + 1)^2")
        return self

    # ----------------------------------------------------------------------------------------
    # Cheap structural helpers.
    def index(self, selection: Tensor | slice | Sequence[int], stand_ins: Collection[str] = ()) -> GaussianState:
        """Rows picked by a bool mask [N], an index tensor, a list of indices or a slice.

        Slices return views (no copy); masks and index lists gather. Fields named in `stand_ins`
        are not gathered: they become `stand_in`s of the right shape (for a callee that passes
        them through unread, e.g. a deformation module's `passed_through()` fields).
        """
        if isinstance(selection, slice):
            return GaussianState(*(getattr(self, f)[selection] for f in _FIELDS))
        if not isinstance(selection, Tensor):
            selection = torch.as_tensor(selection, dtype=torch.long, device=self.device)
        if selection.dtype == torch.bool and selection.shape != (self.num_gaussians,):
            raise ValueError(
                f"GaussianState.index: bool mask of shape {list(selection.shape)} for "
                f"{self.num_gaussians} Gaussians"
            )
        if not stand_ins:
            return GaussianState(*(getattr(self, f)[selection] for f in _FIELDS))
        rows = int(selection.sum()) if selection.dtype == torch.bool else selection.numel()
        return GaussianState(*(stand_in(getattr(self, f), rows) if f in stand_ins else getattr(self, f)[selection]
                               for f in _FIELDS))

    @staticmethod
    def cat(states: Sequence[GaussianState]) -> GaussianState:
        """Concatenate along the Gaussian axis (returns the single input unchanged)."""
        if len(states) == 0:
            raise ValueError("GaussianState.cat: no states given")
        if len(states) == 1:
            return states[0]
        return GaussianState(*(torch.cat([getattr(s, f) for s in states], 0) for f in _FIELDS))

    def replace(self, **changes: Tensor) -> GaussianState:
        """A copy with some fields replaced (the others are shared, not copied)."""
        return dataclasses.replace(self, **changes)

    def detach(self) -> GaussianState:
        return GaussianState(*(getattr(self, f).detach() for f in _FIELDS))

    def to(self, *args, **kwargs) -> GaussianState:
        return GaussianState(*(getattr(self, f).to(*args, **kwargs) for f in _FIELDS))
