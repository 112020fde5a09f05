"""The densification-strategy role (a mapper part): how the map's rows change besides the
optimiser's updates, following gsplat's Strategy.

The trainer owns the parameters and the optimiser state; a strategy gets hooks at fixed points
of training and edits the map only through the `MapEdit` it is handed (append, remove,
duplicate, split, reset opacity, update), which keeps every per-row state aligned. Hooks:

- `admit(new, view)`: which of a keyframe's Gaussians enter the map (before they are added);
- `after_keyframe(edit, rows)`: once they are in (rows `rows`);
- `step_post_backward(edit, info)`: after each training step's backward pass and optimiser
  update (gradients in `info`), e.g. accumulate statistics, densify or prune on a schedule;
- `finish(edit)`: after the last training step.

Every strategy also has the growth controls of `StrategyConfig`: `skip_covered` (no new
Gaussian where the map already explains the keyframe) and the memory guard `max_gaussians`.
"""

from __future__ import annotations

import logging
import math
from abc import ABC
from dataclasses import dataclass
from typing import Callable

import torch

from slamkit.map.gaussian_map import GaussianRows
from slamkit.map.editing import MapEdit
from slamkit.map.rendering import RenderOutput, covered_by_render
from slamkit.roles.config import PluginConfig, require
from slamkit.roles.mapping import TrainingView
from slamkit.types import Camera

log = logging.getLogger(__name__)


@dataclass
class StrategyConfig(PluginConfig):
    """Growth controls every strategy takes (a strategy's config derives from this one).

    skip_covered: a keyframe adds no Gaussian where the map already explains its view: a new
      Gaussian is left out when the map rendered at the keyframe's pose (training resolution)
      has alpha > covered_alpha at its pixel and an expected depth (depth / alpha) within
      covered_depth_tolerance metres of its own.
    covered_alpha, covered_depth_tolerance: those two thresholds (metres for the tolerance).
    max_gaussians: memory guard, null = unlimited (the paper's behaviour). When a keyframe's
      Gaussians (or densification) take the map above this many, the least opaque Gaussians
      (the keyframe's own new Gaussians, whose opacity is still the initial value and says
      nothing yet, go last) are pruned until (1 - memory_guard_margin) x max_gaussians remain,
      so a guarded run does not prune at every keyframe. A Gaussian costs up to ~1 kB of
      resident memory while mapping (0.7-0.9 kB measured, docs/results.md).
    memory_guard_margin: the fraction of max_gaussians freed below the cap when the guard prunes.
    """

    skip_covered: bool = False
    covered_alpha: float = 0.9
    covered_depth_tolerance: float = 0.05
    max_gaussians: int | None = None
    memory_guard_margin: float = 0.1

    def validate(self) -> None:
        require(0 < self.covered_alpha < 1, "strategy.covered_alpha", "in (0, 1)", self.covered_alpha)
        require(self.covered_depth_tolerance > 0, "strategy.covered_depth_tolerance", "> 0 metres",
                self.covered_depth_tolerance)
        require(self.max_gaussians is None or self.max_gaussians > 0, "strategy.max_gaussians",
                "null (unlimited) or an integer > 0", self.max_gaussians)
        require(0 <= self.memory_guard_margin < 1, "strategy.memory_guard_margin", "in [0, 1)",
                self.memory_guard_margin)


@dataclass
class KeyframeView:
    """The keyframe whose Gaussians are being admitted: its camera at the training resolution,
    world_to_camera (4,4) float32 tensor, and `render()`, the current map rendered from it
    (computed on first call)."""

    camera: Camera
    world_to_camera: torch.Tensor
    render: Callable[[], RenderOutput]


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


class DensifyStrategy(ABC):
    """Base of every densification strategy (see the module docstring). Per-row statistics go
    in `state` (name -> tensor with one row per map Gaussian), which the row operations keep
    aligned; counters for metrics.json in `stats`."""

    def __init__(self, cfg: StrategyConfig):
        self.cfg = cfg
        self.state: dict[str, torch.Tensor] = {}
        self.stats: dict[str, int] = {"pruned_by_memory_guard": 0, "memory_guard_prunings": 0}

    def admit(self, new: GaussianRows, view: KeyframeView) -> torch.Tensor | None:
        """Which new Gaussians enter the map (bool mask), None for all: with skip_covered, those
        whose pixel the map does not already cover at a consistent depth."""
        if not self.cfg.skip_covered or len(new) == 0:
            return None
        covered = covered_by_render(new.means, view.render(), view.world_to_camera, view.camera,
                                    self.cfg.covered_alpha, self.cfg.covered_depth_tolerance)
        return ~covered

    def after_keyframe(self, edit: MapEdit, new_rows: slice) -> None:
        """A keyframe's Gaussians are in the map at `new_rows`: enforce the memory guard."""
        self.enforce_memory_guard(edit, protect=new_rows)

    def step_post_backward(self, edit: MapEdit, info: StepInfo) -> None:
        """After a training step's backward pass and optimiser update. Nothing by default."""

    def finish(self, edit: MapEdit) -> None:
        """After the last training step. Nothing by default."""

    def metrics(self) -> dict[str, int]:
        """Counters for the run's metrics.json."""
        return dict(self.stats)

    def state_dict(self) -> dict:
        """The per-row statistics and counters, for a map checkpoint."""
        return {"state": dict(self.state), "stats": dict(self.stats)}

    def load_state_dict(self, state: dict) -> None:
        """Take back a `state_dict()`; `state` is updated in place (the MapEdit holds it)."""
        self.state.update({k: torch.as_tensor(v) for k, v in state.get("state", {}).items()})
        self.stats.update(state.get("stats", {}))

    def enforce_memory_guard(self, edit: MapEdit, protect: slice | None = None) -> int:
        """When the map holds more than max_gaussians, remove the least opaque Gaussians (ties:
        older rows first) until floor((1 - memory_guard_margin) max_gaussians) remain; rows in
        `protect` go only when the others do not make room. Returns the number removed."""
        cap, n = self.cfg.max_gaussians, len(edit)
        if cap is None or n <= cap:
            return 0
        excess = n - max(1, int(cap * (1.0 - self.cfg.memory_guard_margin)))
        key = torch.nan_to_num(edit.params["opacity_logits"].clone(), nan=-math.inf)
        if protect is not None:
            key[protect] = math.inf
        drop = torch.zeros(n, dtype=torch.bool, device=key.device)
        drop[torch.sort(key, stable=True).indices[:excess]] = True
        edit.remove(drop)
        self.stats["pruned_by_memory_guard"] += excess
        self.stats["memory_guard_prunings"] += 1
        log.debug("memory guard: pruned the %d least opaque Gaussians, %d left", excess, len(edit))
        return excess
