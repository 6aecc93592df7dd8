"""Adam bookkeeping for per-Gaussian parameters whose rows change (densify, prune, reset).

Each per-Gaussian tensor is the single parameter of a named optimizer group (4DGS's layout).
When rows are added, removed or reset, the parameter is replaced by a new ``nn.Parameter`` and
its per-row Adam moments are mapped the same way, while scalar state such as ``step`` is kept,
as 4DGS does. Loading a saved optimizer state matches groups by name, so a 4DGS state dict
(8 groups) loads into an optimizer that has extra groups (plugin parameters).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor, nn


def find_group(optimizer: torch.optim.Optimizer, name: str) -> dict[str, Any]:
    """The parameter group called ``name`` (``ValueError`` if there is none)."""
    for group in optimizer.param_groups:
        if group.get("name") == name:
            return group
    names = [g.get("name") for g in optimizer.param_groups]
    raise ValueError(f"optimizer has no parameter group named {name!r} (groups: {names})")


def swap_group_param(
    optimizer: torch.optim.Optimizer,
    name: str,
    new_param: nn.Parameter,
    map_rows: Callable[[Tensor], Tensor] | None,
) -> None:
    """Make ``new_param`` the parameter of single-parameter group ``name``.

    Per-row state tensors (those shaped like the old parameter) go through ``map_rows``; with
    ``map_rows=None`` they restart at zero (4DGS's ``replace_tensor_to_optimizer``).
    """
    group = find_group(optimizer, name)
    if len(group["params"]) != 1:
        raise ValueError(f"optimizer group {name!r} has {len(group['params'])} parameters, expected 1")
    old = group["params"][0]
    state = optimizer.state.pop(old, None)
    group["params"][0] = new_param
    if not state:
        return
    for key, value in state.items():
        if isinstance(value, Tensor) and value.shape == old.shape and value.dim() > 0:
            state[key] = torch.zeros_like(new_param) if map_rows is None else map_rows(value)
    optimizer.state[new_param] = state


def load_state_by_group_name(optimizer: torch.optim.Optimizer, saved: Mapping[str, Any], source: str) -> None:
    """Load an optimizer ``state_dict`` matching parameter groups by their "name".

    Groups of ``optimizer`` absent from ``saved`` keep their current settings and start with
    empty state; saved groups absent from ``optimizer`` are an error, as are groups whose
    parameter counts or state shapes differ. ``source`` names the origin in error messages.
    """
    try:
        saved_groups = list(saved["param_groups"])
        saved_state = dict(saved["state"])
    except (KeyError, TypeError) as err:
        raise ValueError(f"{source}: optimizer state is not an optimizer state_dict ({err})") from None
    by_name = {}
    for group in saved_groups:
        if "name" not in group:
            raise ValueError(f"{source}: optimizer parameter group without a 'name'")
        by_name[group["name"]] = group
    current = {g.get("name"): g for g in optimizer.param_groups}
    unknown = [n for n in by_name if n not in current]
    if unknown:
        raise ValueError(f"{source}: optimizer groups {unknown} do not exist in this model (groups: {list(current)})")

    merged_groups, merged_state, next_id = [], {}, 0
    for group in optimizer.param_groups:
        name = group.get("name")
        params = group["params"]
        ids = list(range(next_id, next_id + len(params)))
        next_id += len(params)
        if name in by_name:
            old = by_name[name]
            if len(old["params"]) != len(params):
                raise ValueError(
                    f"{source}: optimizer group {name!r} has {len(old['params'])} parameters, "
                    f"the model has {len(params)}"
                )
            for new_id, old_id, param in zip(ids, old["params"], params):
                if old_id in saved_state:
                    entry = saved_state[old_id]
                    for key, value in entry.items():
                        if isinstance(value, Tensor) and value.dim() > 0 and value.shape != param.shape:
                            raise ValueError(
                                f"{source}: optimizer state {key!r} of group {name!r} has shape "
                                f"{list(value.shape)}, the parameter has {list(param.shape)}"
                            )
                    merged_state[new_id] = entry
            settings = {k: v for k, v in old.items() if k != "params"}
        else:
            settings = {k: v for k, v in group.items() if k != "params"}
        merged_groups.append({**settings, "params": ids})
    optimizer.load_state_dict({"state": merged_state, "param_groups": merged_groups})
