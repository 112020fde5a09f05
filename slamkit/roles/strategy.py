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
Gaussian where the map already explains the keyframe, on by default: the map is bounded by the
scene, not by how long the camera looks at it) and the memory guard `max_gaussians`.
"""

from __future__ import annotations

import enum
import logging
import math
from abc import ABC
from dataclasses import dataclass
from typing import Callable

import torch

from slamkit.map.gaussian_map import GaussianRows
from slamkit.map.editing import MapEdit
from slamkit.map.coverage import DepthTolerance, covered_by_render, occupied_by_centres
from slamkit.map.rendering import RenderOutput
from slamkit.roles.config import PluginConfig, require
from slamkit.roles.dataset import SensorProfile
from slamkit.roles.mapping import TrainingView
from slamkit.types import Camera

log = logging.getLogger(__name__)


class CoverageTest(enum.Enum):
    """Where `skip_covered` takes the map to explain a keyframe's view (`slamkit.map.coverage`):
    centres: a map Gaussian's centre projects within covered_cell / sqrt(2) pixels of the new
    Gaussian's (input image) at its camera depth, or closer at a depth off by up to the depth
    tolerance (an ellipse, `slamkit.map.coverage.occupied_by_centres`); render: the map
    rendered from the keyframe (training resolution) has alpha > covered_alpha at its pixel and
    an expected depth within the depth tolerance; either: one of the two. The depth tolerance:
    max(covered_depth_tolerance, covered_depth_quadratic z^2) at camera depth z."""

    centres = "centres"
    render = "render"
    either = "either"


@dataclass
class StrategyConfig(PluginConfig):
    """Growth controls every strategy takes (a strategy's config derives from this one).

    skip_covered: a keyframe adds no Gaussian where the map already explains its view (the test
      is `coverage`), except those the tracker aligns to (trackable: new surface for the
      tracking target, which the keyframe's own overlap test already limits), so tracking is
      unchanged. Off, every keyframe adds all its Gaussians and a camera revisiting a scene
      grows the map without bound.
    coverage: the test (CoverageTest): centres (no render, and no training needed, so it
      bounds the map in real-time mode too), render, or either.
    covered_cell: input-image pixels; the cell of the centres test, whose disc (radius cell /
      sqrt(2)) holds a map centre wherever the map's centres are spaced at most a cell apart in
      the view at the point's depth (null = the dataset's `SensorProfile.tracking_pixel_stride`,
      the spacing of a keyframe's Gaussians: 5 TUM, 10 Replica, so a view holds about one
      Gaussian per cell and surface, as one keyframe gives it). Smaller cells allow a denser map
      (half the stride: up to ~4x) that a looped sequence fills only slowly, pass after pass
      (docs/results.md).
    covered_centres: how many map centres the centres test needs in a point's ellipse to count
      it explained: a view holds up to about this many Gaussians per cell and surface.
    covered_alpha: the render test's alpha threshold.
    covered_depth_tolerance: metres; how far a point's camera depth may be from the map's (the
      render's expected depth, or a centre's) to count as explained, in both tests, at least.
    covered_depth_quadratic: 1/metres; beyond sqrt(covered_depth_tolerance / this) the tolerance
      is this x z^2 (z the camera depth, metres), as the depth noise of structured-light sensors
      grows (Kinect v1: ~4 cm quantisation at 3.7 m); 0: covered_depth_tolerance at any depth.
    max_gaussians: memory guard, null = unlimited (the paper's behaviour). When a keyframe's
      Gaussians (or densification) take the map above this many, the least opaque Gaussians
      (the keyframe's own new Gaussians, whose opacity is still the initial value and says
      nothing yet, go last) are pruned until (1 - memory_guard_margin) x max_gaussians remain,
      so a guarded run does not prune at every keyframe. A Gaussian costs up to ~1 kB of
      resident memory while mapping (0.7-0.9 kB measured, docs/results.md).
    memory_guard_margin: the fraction of max_gaussians freed below the cap when the guard prunes.
    """

    skip_covered: bool = True
    coverage: CoverageTest = CoverageTest.centres
    covered_cell: float | None = None
    covered_centres: int = 1
    covered_alpha: float = 0.9
    covered_depth_tolerance: float = 0.05
    covered_depth_quadratic: float = 0.01
    max_gaussians: int | None = None
    memory_guard_margin: float = 0.1

    def validate(self) -> None:
        require(self.covered_cell is None or self.covered_cell > 0, "strategy.covered_cell",
                "null or > 0 pixels", self.covered_cell)
        require(self.covered_centres >= 1, "strategy.covered_centres", "an integer >= 1", self.covered_centres)
        require(0 < self.covered_alpha < 1, "strategy.covered_alpha", "in (0, 1)", self.covered_alpha)
        require(self.covered_depth_tolerance > 0, "strategy.covered_depth_tolerance", "> 0 metres",
                self.covered_depth_tolerance)
        require(self.covered_depth_quadratic >= 0, "strategy.covered_depth_quadratic", ">= 0 per metre",
                self.covered_depth_quadratic)
        require(self.max_gaussians is None or self.max_gaussians > 0, "strategy.max_gaussians",
                "null (unlimited) or an integer > 0", self.max_gaussians)
        require(0 <= self.memory_guard_margin < 1, "strategy.memory_guard_margin", "in [0, 1)",
                self.memory_guard_margin)

    def with_sensor(self, sensor: SensorProfile) -> StrategyConfig:
        """Fills covered_cell; a strategy's config that fills its own fields calls this first."""
        return self.fill_nulls(covered_cell=default_covered_cell(sensor))


def default_covered_cell(sensor: SensorProfile) -> float:
    """The centres test's cell (input pixels) for a sensor: its tracking pixel stride."""
    return float(sensor.tracking_pixel_stride)


@dataclass
class KeyframeView:
    """The keyframe whose Gaussians are being admitted: its camera at the training resolution,
    world_to_camera (4,4) float32 tensor, `render()`, the current map rendered from it (computed
    on first call), its camera at the input resolution (None: `camera`), and the map's Gaussian
    centres (M,3) world metres (None: not given, an empty map)."""

    camera: Camera
    world_to_camera: torch.Tensor
    render: Callable[[], RenderOutput]
    input_camera: Camera | None = None
    centres: torch.Tensor | None = None


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
        self.stats: dict[str, int] = {"pruned_by_memory_guard": 0, "memory_guard_prunings": 0,
                                      "skipped_as_covered": 0}

    def admit(self, new: GaussianRows, view: KeyframeView) -> torch.Tensor | None:
        """Which new Gaussians enter the map (bool mask), None for all: with skip_covered, the
        trackable ones and those where the map does not explain the view (`covered`)."""
        if not self.cfg.skip_covered or len(new) == 0:
            return None
        enter = ~self.covered(new.means, view) | new.trackable.to(new.means.device)
        self.stats["skipped_as_covered"] += int((~enter).sum())
        return enter

    def covered(self, points: torch.Tensor, view: KeyframeView) -> torch.Tensor:
        """(N,) bool: the world points (N,3, metres) where the map already explains the
        keyframe's view, by the configured `coverage` test."""
        cfg, test = self.cfg, CoverageTest(self.cfg.coverage)
        tolerance = DepthTolerance(cfg.covered_depth_tolerance, cfg.covered_depth_quadratic)
        covered = torch.zeros(len(points), dtype=torch.bool, device=points.device)
        if test is not CoverageTest.render and view.centres is not None:
            cell = cfg.covered_cell if cfg.covered_cell is not None else default_covered_cell(SensorProfile())
            covered |= occupied_by_centres(points, view.centres, view.world_to_camera, view.input_camera or view.camera,
                                           cell, tolerance, cfg.covered_centres)
        if test is not CoverageTest.centres:
            covered |= covered_by_render(points, view.render(), view.world_to_camera, view.camera,
                                         cfg.covered_alpha, tolerance)
        return covered

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
