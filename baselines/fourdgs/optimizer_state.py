"""Adam bookkeeping for per-Gaussian parameters whose rows change (densify, prune, reset).

Each per-Gaussian tensor is the single parameter of a named optimizer group (4DGS's layout).
When rows are added, removed or reset, the parameter is replaced by a new ``nn.Parameter`` and
its per-row Adam moments are mapped the same way, while scalar state such as ``step`` is kept,
as 4DGS does. Loading a saved optimizer state matches groups by name, so a 4DGS state dict
(8 groups) loads into an optimizer that has extra groups (plugin parameters).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
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


def _groups_by_name(saved: Mapping[str, Any], source: str) -> tuple[dict[str, dict], dict]:
    try:
        saved_groups = list(saved["param_groups"])
        saved_state = dict(saved["state"])
    except (KeyError, TypeError) as err:
        raise ValueError(f"{source}: optimizer state is not an optimizer state_dict ({err})") from None
    by_name = {}
    for group in saved_groups:
        if not isinstance(group, Mapping) or "name" not in group:
            raise ValueError(f"{source}: optimizer parameter group without a 'name'")
        by_name[group["name"]] = group
    return by_name, saved_state


def check_state_by_group_name(
    saved: Mapping[str, Any], expected: Mapping[str, Sequence[torch.Size]], source: str
) -> None:
    """Raise ``ValueError`` unless a saved optimizer ``state_dict`` fits groups ``expected``
    (name -> parameter shapes): known group names, parameter counts and per-row state shapes."""
    by_name, saved_state = _groups_by_name(saved, source)
    unknown = [n for n in by_name if n not in expected]
    if unknown:
        raise ValueError(f"{source}: optimizer groups {unknown} do not exist in this model (groups: {list(expected)})")
    for name, group in by_name.items():
        shapes = expected[name]
        if len(group["params"]) != len(shapes):
            raise ValueError(
                f"{source}: optimizer group {name!r} has {len(group['params'])} parameters, the model has {len(shapes)}"
            )
        for param_id, shape in zip(group["params"], shapes):
            for key, value in saved_state.get(param_id, {}).items():
                if isinstance(value, Tensor) and value.dim() > 0 and value.shape != shape:
                    raise ValueError(
                        f"{source}: optimizer state {key!r} of group {name!r} has shape {list(value.shape)}, "
                        f"the parameter has {list(shape)}"
                    )


def load_state_by_group_name(optimizer: torch.optim.Optimizer, saved: Mapping[str, Any], source: str) -> None:
    """Load an optimizer ``state_dict`` matching parameter groups by their "name".

    Groups of ``optimizer`` absent from ``saved`` keep their current settings and start with
    empty state; saved groups absent from ``optimizer`` are an error, as are groups whose
    parameter counts or state shapes differ. ``source`` names the origin in error messages.
    """
    expected = {g.get("name"): [p.shape for p in g["params"]] for g in optimizer.param_groups}
    check_state_by_group_name(saved, expected, source)
    by_name, saved_state = _groups_by_name(saved, source)
    merged_groups, merged_state, next_id = [], {}, 0
    for group in optimizer.param_groups:
        name = group.get("name")
        ids = list(range(next_id, next_id + len(group["params"])))
        next_id += len(ids)
        if name in by_name:
            old = by_name[name]
            for new_id, old_id in zip(ids, old["params"]):
                if old_id in saved_state:
                    merged_state[new_id] = saved_state[old_id]
            settings = {k: v for k, v in old.items() if k != "params"}
        else:
            settings = {k: v for k, v in group.items() if k != "params"}
        merged_groups.append({**settings, "params": ids})
    optimizer.load_state_dict({"state": merged_state, "param_groups": merged_groups})
