"""The optimiser part: updates the map's parameters from a training step's gradients."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, Callable

import torch

from slamkit.map.gaussian_map import RowMotion


class MapOptimizer(ABC):
    """Updates the map's parameters from one training step's gradients.

    Its state is per map row (e.g. Adam's moments), so it must follow the rows as the map grows
    and shrinks: the shared row operations (`slamkit.roles.map_edit.MapEdit`) call `edit_rows`
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

    def move_rows(self, motion: RowMotion) -> None:
        """The map moved its rows rigidly (`GaussianMap.move_rows`, a loop closure's correction):
        carry each moved row's state along. By default the moved rows' state of the means and
        quaternions is zeroed, as a new row's: right for any optimiser, at the cost of its
        history (an optimiser with moments rotates them instead: `rotated_moments`)."""
        moved = motion.moved

        def zero(name: str, v: torch.Tensor) -> torch.Tensor:
            if name not in ("means", "quats"):
                return v
            v = v.clone()
            v[moved.to(v.device)] = 0
            return v

        self.edit_rows(zero)

    def row_state(self) -> dict[str, list[torch.Tensor]]:
        """Copies of the per-row state tensors, by parameter name (for inspection and tests)."""
        found: dict[str, list[torch.Tensor]] = {}

        def copy(name: str, v: torch.Tensor) -> torch.Tensor:
            found.setdefault(name, []).append(v.clone())
            return v

        self.edit_rows(copy)
        return found


def rotated_moments(linear: torch.Tensor, first: torch.Tensor | None,
                    second: torch.Tensor | None) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """Adam's moments of parameter rows that a rigid motion replaced by `linear @ row` (linear:
    (N,d,d) orthogonal, `RowMotion.rotations` for the means, `quat_maps` for the quaternions).
    The loss's gradient with respect to a moved row is `linear @` the unmoved one's, so the first
    moment (a running mean of gradients) is rotated exactly; the second is element-wise (a
    running mean of squared components), which no rotation carries exactly: it becomes
    `(linear * linear) @ second`, exact when the gradient's components are uncorrelated, and
    for a motion without rotation. Zeroing them instead would make each moved row's next steps
    up to (1 - beta1) / sqrt(1 - beta2) ~ 3 learning rates long, on every Gaussian a loop moves."""
    def apply(matrix: torch.Tensor, v: torch.Tensor | None) -> torch.Tensor | None:
        if v is None:
            return None
        matrix = matrix.to(v.device)
        return torch.einsum("nij,nj->ni", matrix, v.double()).to(v.dtype)

    return apply(linear, first), apply(linear * linear, second)
