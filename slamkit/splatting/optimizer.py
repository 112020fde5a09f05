"""The optimiser part: updates the map's parameters from a training step's gradients."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, Callable

import torch


class MapOptimizer(ABC):
    """Updates the map's parameters from one training step's gradients.

    Its state is per map row (e.g. Adam's moments), so it must follow the rows as the map grows
    and shrinks: the shared row operations (`slamkit.splatting.ops.MapEdit`) call `edit_rows`
    and `reset`, never a strategy directly."""

    @abstractmethod
    def step(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> None:
        """Update `params` (the map's leaf tensors by name, `slamkit.map.gaussian_map.PARAMETERS`)
        in place from `grads` (same names and shapes; a missing name had no gradient)."""

    @abstractmethod
    def num_rows(self) -> int:
        """The map rows its state covers."""

    @abstractmethod
    def edit_rows(self, edit: Callable[[str, torch.Tensor], torch.Tensor]) -> None:
        """Replace each per-row state tensor `v` of parameter `name` by `edit(name, v)` (first
        dimension = rows; the result may have a different number of rows)."""

    @abstractmethod
    def reset(self) -> None:
        """Forget all state (zero rows)."""

    def state_dict(self) -> dict[str, Any]:
        """The optimiser's state (per-row moments, step counts) for a map checkpoint: JSON values
        and tensors."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()` (CPU tensors; `edit_rows` moves them to the map's device)."""

    def row_state(self) -> dict[str, list[torch.Tensor]]:
        """Copies of the per-row state tensors, by parameter name (for inspection and tests)."""
        found: dict[str, list[torch.Tensor]] = {}

        def copy(name: str, v: torch.Tensor) -> torch.Tensor:
            found.setdefault(name, []).append(v.clone())
            return v

        self.edit_rows(copy)
        return found
