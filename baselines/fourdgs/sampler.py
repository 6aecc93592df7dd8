"""4DGS's camera sampling: draw cameras at random without replacement, refill when exhausted.

The generator is our own (seeded, saved in training checkpoints) so that a resumed run draws the
same cameras as an uninterrupted one.
"""
from __future__ import annotations

from typing import Any, Sequence, TypeVar

import torch

T = TypeVar("T")


class CameraSampler:
    """Random batches over a list of items, each item once per pass (4DGS's viewpoint stack)."""

    def __init__(self, items: Sequence[T], seed: int = 0) -> None:
        if not items:
            raise ValueError("CameraSampler needs at least one camera")
        self.items = list(items)
        self.generator = torch.Generator().manual_seed(seed)
        self.stack: list[int] = []

    def next_batch(self, batch_size: int) -> list[T]:
        """`batch_size` items; a pass ends when every item was drawn once."""
        batch = []
        for _ in range(batch_size):
            if not self.stack:
                self.stack = list(range(len(self.items)))
            pick = int(torch.randint(len(self.stack), (1,), generator=self.generator))
            batch.append(self.items[self.stack.pop(pick)])
        return batch

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state(), "stack": list(self.stack)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a saved state (its stack must index `items`: the trainer checks camera names first)."""
        stack = [int(i) for i in state["stack"]]
        bad = [i for i in stack if not 0 <= i < len(self.items)]
        if bad:
            raise ValueError(f"sampler state names item {bad[0]} but there are {len(self.items)} items")
        self.generator.set_state(state["generator"])
        self.stack = stack
