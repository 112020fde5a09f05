"""The strategy part (gsplat's Strategy): how the map's rows change besides the optimiser's
updates.

The trainer owns the parameters and the optimiser state; a strategy gets hooks at fixed points
of training and edits the map only through the `MapEdit` it is handed (append, remove,
duplicate, split, reset opacity, update), which keeps every per-row state aligned:
`step_post_backward(edit, info)` after each step's backward pass and optimiser update
(gradients in `info`: accumulate statistics, densify or prune on a schedule), `finish(edit)`
after the last step. Which of a keyframe's Gaussians enter the map (`mapper.admission.*`) and
the memory cap (`mapper.memory_cap.*`) are the 3DGS trainer's, whatever the strategy.
"""

from __future__ import annotations

from abc import ABC
from dataclasses import dataclass
from typing import Any

import torch

from slamkit.config import PluginConfig, RunContext
from slamkit.roles.map_edit import MapEdit
from slamkit.roles.rendering import RenderOutput
from slamkit.roles.training_view import TrainingView


@dataclass
class StrategyConfig(PluginConfig):
    """Base of every strategy's config."""


@dataclass
class StepInfo:
    """One finished training step. step: steps taken so far, this one included. view: the
    keyframe trained on. render: its render. grads: the loss's gradient with respect to each
    map parameter (rows as at the step's start; the map may have grown since). loss: its
    value."""

    step: int
    view: TrainingView
    render: RenderOutput
    grads: dict[str, torch.Tensor]
    loss: float


class Strategy(ABC):
    """Base of every densification strategy (see the module docstring). Per-row statistics go
    in `state` (name -> tensor with one row per map Gaussian), which the row operations keep
    aligned; counters for metrics.json in `stats`."""

    def __init__(self, cfg: StrategyConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        self.state: dict[str, torch.Tensor] = {}
        self.stats: dict[str, int] = {}

    def step_post_backward(self, edit: MapEdit, info: StepInfo) -> None:
        """After a training step's backward pass and optimiser update. Nothing by default."""

    def finish(self, edit: MapEdit) -> None:
        """After the last training step. Nothing by default."""

    def metrics(self) -> dict[str, int]:
        """Counters for the run's metrics.json."""
        return dict(self.stats)

    def state_dict(self) -> dict[str, Any]:
        """The per-row statistics and counters, for a map checkpoint."""
        return {"state": dict(self.state), "stats": dict(self.stats)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()`; `state` is updated in place (the MapEdit holds it)."""
        self.state.update({k: torch.as_tensor(v) for k, v in state.get("state", {}).items()})
        self.stats.update({k: v for k, v in state.get("stats", {}).items() if k in self.stats})
