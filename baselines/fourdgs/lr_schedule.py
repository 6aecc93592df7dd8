"""Learning-rate schedules of 4DGS/3DGS (utils/general_utils.get_expon_lr_func)."""

from __future__ import annotations

import math
from collections.abc import Callable


def get_expon_lr_func(
    lr_init: float,
    lr_final: float,
    lr_delay_steps: int = 0,
    lr_delay_mult: float = 1.0,
    max_steps: int = 1_000_000,
) -> Callable[[int], float]:
    """Log-linear decay from ``lr_init`` (step 0) to ``lr_final`` (step ``max_steps``, then held).

    With ``lr_delay_steps > 0`` the rate is additionally scaled by a factor that eases from
    ``lr_delay_mult`` to 1 along a quarter sine over the first ``lr_delay_steps`` steps. A
    negative step, or both rates 0, gives 0 (a disabled parameter group).
    """
    disabled = lr_init == 0.0 and lr_final == 0.0
    if not disabled and (lr_init <= 0.0 or lr_final <= 0.0):
        # 4DGS would produce NaN learning rates here (log of 0); say so up front instead.
        raise ValueError(
            f"get_expon_lr_func: lr_init ({lr_init}) and lr_final ({lr_final}) must both be > 0, "
            "or both 0 to disable the group"
        )
    if max_steps <= 0:
        raise ValueError(f"get_expon_lr_func: max_steps must be > 0, got {max_steps}")

    def schedule(step: int) -> float:
        if step < 0 or disabled:
            return 0.0
        if lr_delay_steps > 0:
            ramp = min(max(step / lr_delay_steps, 0.0), 1.0)
            delay = lr_delay_mult + (1.0 - lr_delay_mult) * math.sin(0.5 * math.pi * ramp)
        else:
            delay = 1.0
        t = min(max(step / max_steps, 0.0), 1.0)
        return delay * math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)

    return schedule
