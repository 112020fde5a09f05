"""A run's plugins built from its validated config: the dataset first, then, in the run's
context (the dataset's tuning, the mode, the shared map), every other role with its config's
null fields filled (`slamkit.config.resolve_tree`), the mapper with its parts, the loop closure
(`slamkit.run.loop_closing.LoopCloser`).

    dataset, slam, viewer = build_run(["dataset=tum", "dataset.path=PATH"])
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Sequence

from slamkit.config import RunContext, resolve_tree
from slamkit.errors import ConfigError, DataError
from slamkit.map.gaussian_map import GaussianMap
from slamkit.native import available_threads
from slamkit.registry.compose import compose_run, preset_not_applied
from slamkit.registry.discovery import Registry, default_registry
from slamkit.registry.schema import LoopCorrections, Mode, RunConfig
from slamkit.roles import Dataset, Tracker, Viewer
from slamkit.run.boundary import PluginBoundary
from slamkit.run.handover import KeyframeHandovers
from slamkit.run.loop_closing import LoopCloser
from slamkit.run.loop_process import LoopClosureProcess
from slamkit.run.slam import SLAM

log = logging.getLogger(__name__)


@dataclass
class BuiltRun:
    """What `build` made: the dataset, the SLAM system, the viewer, and the run's effective
    config (every null field that the run fills, filled)."""

    dataset: Dataset
    slam: SLAM
    viewer: Viewer
    config: RunConfig


def tracking_threads(cfg: RunConfig) -> int:
    """Threads for the tracking side: one in real-time mode (the mapping thread has the other
    CPUs), else every CPU this process may use (or $OMP_NUM_THREADS)."""
    return 1 if cfg.mode is Mode.realtime else available_threads()


def build(cfg: RunConfig, registry: Registry, names: dict[str, str]) -> BuiltRun:
    """The run's plugins from a validated config; `names` maps each role's and part's path
    (`tracker`, `mapper.rasterizer`) to the chosen plugin's name. A plugin whose constructor
    fails is named in one line (PluginError), as a failure of any of its methods is."""
    for path, skipped in preset_not_applied(cfg.preset, names).items():
        log.warning("preset=%s: its %s settings are for %s, left out for %s=%s (metrics.json: "
                    "settings.preset_not_applied)", cfg.preset, path, " / ".join(skipped["settings_for"]), path,
                    skipped["chosen"])
    boundary = PluginBoundary(names)
    with boundary("dataset", "__init__"):
        dataset = registry.create("dataset", names["dataset"], cfg.dataset)
    if len(dataset) == 0:
        raise DataError(f"dataset {names['dataset']!r} at {cfg.dataset.path!r}: no frames selected")
    dataset.check_camera()
    gaussian_map = GaussianMap(cfg.device())

    def build_default(role: str, name: str) -> Any:
        return registry.create(role, name, None, context)

    context = RunContext(tuning=dataset.tuning, realtime=cfg.mode is Mode.realtime,
                         drops_frames=cfg.mode is Mode.realtime and cfg.realtime.drop_frames,
                         tracking_threads=tracking_threads(cfg), device=str(gaussian_map.device),
                         gaussian_map=gaussian_map, build=build_default, scoring=cfg.eval)
    cfg = resolve_tree(cfg, context)

    def create(path: str, config: Any, **parts) -> Any:
        with boundary(path, "__init__"):
            return registry.create(path.split(".")[-1], names[path], config, context, **parts)

    mapper_parts = registry.get("mapper", names["mapper"]).cls.parts
    parts = {part: create(f"mapper.{part}", getattr(cfg.mapper, part)) for part in mapper_parts}
    tracker = create("tracker", cfg.tracker)
    loop_closer = LoopCloser(_loop_closure(cfg, registry, names, context, create), boundary,
                             at_end=cfg.loop_corrections is LoopCorrections.at_end)
    if loop_closer.active and type(tracker).move_world is Tracker.move_world:
        raise ConfigError(f"loop_closure={names['loop_closure']}: tracker={names['tracker']} cannot follow a loop "
                          "closure's corrections (it does not implement Tracker.move_world); use loop_closure=none "
                          "or tracker=gicp")
    realtime = cfg.mode is Mode.realtime  # the real-time runner's workers train and detect beside `process`
    slam = SLAM(tracker, create("keyframe", cfg.keyframe), create("mapper", cfg.mapper, **parts), gaussian_map,
                cfg.growth, cfg.iterations_per_frame, boundary, loop_closer, beside=realtime,
                handovers=KeyframeHandovers() if realtime and cfg.realtime.keyframe_thread else None)
    return BuiltRun(dataset, slam, create("viewer", cfg.viewer), cfg)


def _loop_closure(cfg: RunConfig, registry: Registry, names: dict[str, str], context: RunContext, create):
    """The run's loop closure: in real time, one that closes loops runs in a process of its own
    at the mapping thread's priority (`slamkit.run.loop_process`); otherwise here."""
    cls = registry.get("loop_closure", names["loop_closure"]).cls
    if context.realtime and cls.closes_loops:
        with PluginBoundary(names)("loop_closure", "__init__"):
            return LoopClosureProcess(cls, cfg.loop_closure, context, cfg.realtime.mapping_priority)
    return create("loop_closure", cfg.loop_closure)


def build_run(overrides: Sequence[str] = (), registry: Registry | None = None) -> tuple[Dataset, SLAM, Viewer]:
    """(dataset, SLAM system, viewer) for `overrides`, built as a `slamkit` run builds them."""
    registry = registry or default_registry()
    cfg, names = compose_run(overrides, registry)
    built = build(cfg, registry, names)
    return built.dataset, built.slam, built.viewer
