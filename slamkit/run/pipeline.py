"""Running SLAM on a dataset: building the roles from config, the frame loop (sequential or
beside a mapping thread, paced like a camera), the progress bar, the viewer, the per-frame log
(frames.csv) and the refinement after the stream; the outputs are `slamkit.run.outputs`.

The algorithm itself is `slamkit.run.slam.SLAM`; this module is the I/O around it.
"""

from __future__ import annotations

import csv
import inspect
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from slamkit.errors import DataError, PluginError, SlamkitError
from slamkit.map.gaussian_map import GaussianMap
from slamkit.metrics import trajectory as evaluation
from slamkit.native import available_threads
from slamkit.registry.discovery import Registry
from slamkit.registry.schema import Mode, RunConfig
from slamkit.run import checkpoint
from slamkit.run.outputs import RunState, rss_mb, summary, write_camera, write_outputs
from slamkit.run.prefetch import UnreadableFrame, prefetched
from slamkit.run.signals import StopSignals
from slamkit.run.slam import SLAM, MappingThread, StepResult
from slamkit.run.viewing import ViewerFeed
from slamkit.types import Frame

__all__ = ["build", "run", "summary", "mapping_threads", "tracking_threads", "InputClock"]

log = logging.getLogger(__name__)


class Blamed:
    """Wraps a plugin so that an exception escaping any of its methods names the plugin:
    the run then stops with a one-line PluginError and writes what it has."""

    def __init__(self, plugin, role: str, name: str):
        self._plugin, self._role, self._name = plugin, role, name

    def __getattr__(self, attr):
        value = getattr(self._plugin, attr)
        if not inspect.ismethod(value):  # data, and parts held as attributes (a mapper's loss)
            return value

        def call(*args, **kwargs):
            try:
                return value(*args, **kwargs)
            except SlamkitError:
                raise
            except Exception as exc:
                # the traceback goes to the log file (INFO), not to the terminal (WARNING and above)
                log.info("%s %r failed in %s()", self._role, self._name, attr, exc_info=True)
                message = f"{self._role} plugin {self._name!r} failed in {attr}(): {type(exc).__name__}: {exc}"
                raise PluginError(message.splitlines()[0]) from exc

        return call


def build(cfg: RunConfig, registry: Registry, names: dict[str, str]):
    """Dataset, SLAM system and viewer from a validated config; `names` maps each role key to
    the selected plugin's name. Every part reads the dataset's sensor profile for its null
    fields; the mapper gets the parts it names (`Mapper.parts`), built from their own groups."""
    dataset = registry.create("dataset", names["dataset"], cfg.dataset)
    if len(dataset) == 0:
        raise DataError(f"dataset {names['dataset']!r} at {cfg.dataset.path!r}: no frames selected")
    dataset.check_camera()
    sensor = dataset.sensor

    def create(role: str, **parts):
        return registry.create(role, names[role], getattr(cfg, role), sensor, **parts)

    parts = {role: create(role) for role in registry.get("mapper", names["mapper"]).cls.parts}
    tracker, policy = create("tracker"), create("keyframe")
    tracker.use_threads(tracking_threads(cfg))
    mapper = create("mapper", **parts)
    slam = SLAM(Blamed(tracker, "tracker", names["tracker"]), Blamed(policy, "keyframe", names["keyframe"]),
                Blamed(mapper, "mapper", names["mapper"]), GaussianMap(cfg.device()), cfg.map.with_sensor(sensor),
                cfg.iterations_per_frame)
    return dataset, slam, create("viewer")


def run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path) -> dict[str, Any]:
    """Run SLAM as configured and write the outputs into `out_dir`; return the metrics."""
    threads_before = torch.get_num_threads()
    torch.set_num_threads(mapping_threads(cfg))
    try:
        return _run(cfg, registry, names, out_dir)
    finally:
        torch.set_num_threads(threads_before)


def _run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    np.random.seed(cfg.seed)
    dataset, slam, viewer = build(cfg, registry, names)
    viewer = ViewerFeed(viewer, names["viewer"], slam.gaussian_map, slam.mapper)
    log.info("%s: %d frames, camera %s; tracker %s, mapper %s, keyframes %s", names["dataset"], len(dataset),
             dataset.camera, names["tracker"], names["mapper"], names["keyframe"])
    write_camera(out_dir / "camera.json", dataset.camera, dataset.depth_trunc)
    state = RunState()
    first = checkpoint.resume(cfg, names, slam, state)  # checkpoint: continue a saved run (resume=RUN_DIR)
    checkpoints = checkpoint.CheckpointWriter(cfg, names, slam, state, dataset, out_dir)
    viewer.start(dataset.camera, out_dir)
    start = time.perf_counter()
    try:
        with StopSignals() as stop, open(out_dir / "frames.csv", "a" if first else "w", newline="") as frames_log:
            _loop(cfg, dataset, slam, state, csv.writer(frames_log), frames_log, viewer, stop, checkpoints, first)
            _refine(slam, cfg.refinement_iterations(), state, stop)
            with stop.deferred():
                slam.mapper.finish()
                state.completed = True
                checkpoints.save("end")  # checkpoint: end of the run
    except KeyboardInterrupt as exc:
        state.error = f"interrupted ({exc or 'SIGINT'})"
        log.warning("run interrupted after %d frames; writing what it has", len(state.poses))
        checkpoints.save("interrupted")  # checkpoint: on SIGINT / SIGTERM
    except Exception as exc:
        state.error = f"{type(exc).__name__}: {exc}"
        log.error("run failed after %d frames: %s; writing what it has", len(state.poses), state.error)
        raise
    finally:
        try:
            metrics = write_outputs(cfg, slam, dataset, state, time.perf_counter() - start, out_dir)
        finally:
            viewer.close()
    return metrics


#: Refinement steps taken between two chances to stop (a stop signal waits for the chunk).
REFINE_CHUNK = 10


def _refine(slam: SLAM, iterations: int, state: RunState, stop: StopSignals) -> None:
    """The map's refinement after the stream: `iterations` more mapping steps, timed apart."""
    if not iterations:
        return
    start, state.refine_iterations = time.perf_counter(), 0
    while state.refine_iterations < iterations:
        with stop.deferred():
            done = slam.mapper.optimize(min(REFINE_CHUNK, iterations - state.refine_iterations))
            state.refine_iterations += done
            state.refine_time_s = time.perf_counter() - start
        if not done:
            break
    log.info("refinement: %d mapping steps in %.1f s", state.refine_iterations, state.refine_time_s)


def mapping_threads(cfg: RunConfig) -> int:
    """Torch threads for mapping: `cfg.mapping_threads`, else torch's default (every CPU, or
    $OMP_NUM_THREADS), less one in real-time mode for the tracking thread (on 2 cores, sharing
    both made the tracker wait)."""
    if cfg.mapping_threads:
        return cfg.mapping_threads
    default = torch.get_num_threads()
    return max(1, default - 1) if cfg.mode is Mode.realtime else default


def tracking_threads(cfg: RunConfig) -> int:
    """Threads for a tracker whose `num_threads` is null: one in real-time mode (the mapping
    thread has the other CPUs), else every CPU this process may use (or $OMP_NUM_THREADS)."""
    return 1 if cfg.mode is Mode.realtime else available_threads()


class InputClock:
    """Paces input like a live camera: frame i arrives `i / fps` seconds after the first."""

    def __init__(self, fps: float | None):
        self.period = 1.0 / fps if fps else 0.0
        self.start: float | None = None

    def wait(self, i: int) -> bool:
        """Sleep until frame i has arrived; True if frame i+1 has arrived too (we are late)."""
        if not self.period:
            return False
        now = time.perf_counter()
        if self.start is None:
            self.start = now
        arrival = self.start + i * self.period
        if now < arrival:
            time.sleep(arrival - now)
            return False
        return now >= arrival + self.period


def _loop(cfg: RunConfig, dataset, slam: SLAM, state: RunState, writer, log_file, viewer: ViewerFeed,
          stop: StopSignals, checkpoints: checkpoint.CheckpointWriter, first: int = 0) -> None:
    """Frames `first`.. of the dataset (a resumed run starts after its checkpoint's last frame)."""
    from tqdm import tqdm

    if not first:
        writer.writerow(["index", "timestamp", "keyframe", "lost", "tracking_ms", "mapping_ms", "iterations",
                         "correspondence_ratio", "num_gaussians", "rss_mb", "note"])
    realtime = cfg.mode is Mode.realtime
    clock = InputClock(cfg.fps_limit if realtime else None)
    mapping = MappingThread(slam.mapper) if realtime else None
    bar = tqdm(total=len(dataset), initial=first, unit="frame", disable=None if cfg.progress else True,
               dynamic_ncols=True)
    start = time.perf_counter()
    try:
        if mapping:
            mapping.start()
        skip_errors = cfg.dataset.on_error.value == "skip"
        for frame in prefetched(dataset, cfg.dataset.prefetch, skip_errors, first):
            if isinstance(frame, UnreadableFrame):
                log.warning("frame %d skipped: %s", frame.index, frame.error)
                state.record_unreadable(frame.timestamp)
                writer.writerow([frame.index, f"{frame.timestamp:.6f}", "none", 1, "", "", 0, "", "", "",
                                 f"unreadable: {frame.error}"])
                bar.update(1)
                continue
            if not state.poses:
                slam.initialize(frame.gt_pose if frame.gt_pose is not None else np.eye(4))
            if clock.wait(frame.index - first) and cfg.drop_frames and state.poses:
                state.record_dropped(frame)
                writer.writerow([frame.index, f"{frame.timestamp:.6f}", "none", 0, "", "", 0, "", "", "", "dropped"])
                bar.update(1)
                continue
            with stop.deferred():  # a frame's step and its record, whole or not at all
                step = slam.track(frame) if realtime else slam.step(frame)
                if mapping:
                    mapping.check()
                state.record(frame, step)
                _log_frame(writer, frame, step, len(slam.gaussian_map))
                checkpoints.after_frame()  # checkpoint: every N keyframes
            viewer.show(frame, step.tracking.pose, step.keyframe, step.tracking.lost)
            bar.update(1)
            every = cfg.eval.running_ate_every
            if every and len(state.poses) % every == 0:
                bar.set_postfix_str(_running_ate(state), refresh=False)
                log_file.flush()
    finally:
        state.stream_time_s += time.perf_counter() - start
        bar.close()
        if mapping:
            _stop_mapping(mapping, state)


def _stop_mapping(mapping: MappingThread, state: RunState) -> None:
    try:
        mapping.stop()
    finally:
        state.mapping_iterations += mapping.iterations
        state.mapping_time_s += mapping.busy_time_s


def _log_frame(writer, frame: Frame, step: StepResult, num_gaussians: int) -> None:
    result = step.tracking
    writer.writerow([frame.index, f"{frame.timestamp:.6f}", step.keyframe.value, int(result.lost),
                     f"{1e3 * step.tracking_time_s:.2f}", f"{1e3 * step.mapping_time_s:.2f}",
                     step.mapping_iterations, _fmt(result.correspondence_ratio), num_gaussians,
                     f"{rss_mb():.1f}", result.stats.get("lost_reason", "")])
    if result.lost:
        log.warning("frame %d lost: %s", frame.index, result.stats.get("lost_reason", "?"))


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.4f}"


def _running_ate(state: RunState) -> str:
    result = evaluation.ate(np.array(state.poses), state.gt_poses)
    return "ATE n/a" if result.rmse_m is None else f"ATE {100 * result.rmse_m:.2f} cm"


