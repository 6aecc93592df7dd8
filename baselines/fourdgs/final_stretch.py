"""The final-stretch rule: a saved model never sits right after an opacity reset or a densification.

4DGS resets every opacity to <= 0.01 each ``opacity_reset_interval`` iterations and densifies every
``densification_interval``; when such a step lands on (or just before) the iteration whose model
is saved and evaluated, that model is collapsed (seen: lego at ``--iterations 3000`` with the
3000-iteration reset interval scores 12.4 dB against 25.1 dB at 2900). The rule, in the fine
stage only (the coarse stage is always followed by the fine stage, which recovers):

- no opacity reset within the last ``min(opacity_reset_interval, RESET_RECOVERY_ITERATIONS)``
  iterations before a *kept* iteration (the stage's final iteration and every
  ``--save_iterations`` entry), the kept iteration itself included;
- no densification and no pruning at a kept iteration.

``--test_iterations`` are not kept iterations: they measure the run and must not change it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

RESET_RECOVERY_ITERATIONS = 500


@dataclass(frozen=True)
class FinalStretch:
    """Which schedule steps are allowed at one iteration (see the module docstring)."""

    allow_reset: bool = True
    allow_densify: bool = True  # densification and pruning

    @property
    def restricted(self) -> bool:
        return not (self.allow_reset and self.allow_densify)


def reset_recovery_window(opt: Any) -> int:
    """Iterations before a kept iteration in which no opacity reset may fire."""
    return max(1, min(int(opt.opacity_reset_interval), RESET_RECOVERY_ITERATIONS))


def final_stretch(opt: Any, iteration: int, stage: str, stage_total: int,
                  save_iterations: Iterable[int]) -> FinalStretch:
    """The steps allowed at ``iteration`` of ``stage`` (``stage_total`` iterations long)."""
    if stage != "fine":
        return FinalStretch()
    kept = sorted({int(stage_total), *(int(s) for s in save_iterations if 0 < int(s) <= stage_total)})
    window = reset_recovery_window(opt)
    allow_reset = not any(k - window < iteration <= k for k in kept)
    return FinalStretch(allow_reset=allow_reset, allow_densify=iteration not in kept)
