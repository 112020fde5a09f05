"""Running SLAM on a dataset: building the roles from config, the progress bar, the viewer, the
run outputs (trajectory.txt, keyframes.txt, camera.json, metrics.json, frames.csv,
trajectory.png) and evaluation.

The algorithm itself is `slamkit.run.slam.SLAM`; this module is the I/O around it.
"""

from __future__ import annotations

import csv
import inspect
import json
import logging
import os
import signal
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from slamkit.metrics import trajectory as evaluation
from slamkit.registry.schema import Mode, RunConfig
from slamkit.errors import DataError, PluginError, SlamkitError
from slamkit.map.gaussian_map import GaussianMap
from slamkit.native import available_threads
from slamkit.run.prefetch import UnreadableFrame, prefetched
from slamkit.registry.discovery import Registry
from slamkit.run.slam import SLAM, MappingThread, StepResult
from slamkit.formats.tum import write_tum_trajectory
from slamkit.types import Frame
from slamkit.run.viewing import ViewerFeed

log = logging.getLogger(__name__)


@dataclass
class RunState:
    """What a run has produced so far; written out even when the run stops early."""

    timestamps: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    gt_poses: list[np.ndarray | None] = field(default_factory=list)
    keyframe_rows: list[int] = field(default_factory=list)  # indices into poses of the keyframes
    num_keyframes: int = 0
    lost_frames: int = 0
    dropped_frames: int = 0
    mapping_iterations: int = 0
    tracking_time_s: float = 0.0
    mapping_time_s: float = 0.0
    stream_time_s: float = 0.0  # from the first frame to the last one tracked
    refine_iterations: int = 0  # mapping steps after the stream
    refine_time_s: float = 0.0
    completed: bool = False
    error: str | None = None

    def record_unreadable(self, timestamp: float) -> None:
        """A frame that could not be read (dataset.on_error=skip): lost, keeps the last pose."""
        self.timestamps.append(timestamp)
        self.poses.append(self.poses[-1] if self.poses else np.full((4, 4), np.nan))
        self.gt_poses.append(None)
        self.lost_frames += 1

    def record_dropped(self, frame: Frame) -> None:
        """A frame that arrived while the tracker was busy (real-time mode, drop_frames): it
        keeps the last pose, so the trajectory still has one line per input frame."""
        self.timestamps.append(frame.timestamp)
        self.poses.append(self.poses[-1])
        self.gt_poses.append(frame.gt_pose)
        self.dropped_frames += 1

    def record(self, frame: Frame, step: StepResult) -> None:
        self.timestamps.append(frame.timestamp)
        self.poses.append(step.tracking.pose)
        self.gt_poses.append(frame.gt_pose)
        if step.keyframe:
            self.keyframe_rows.append(len(self.poses) - 1)
        self.num_keyframes += bool(step.keyframe)
        self.lost_frames += step.tracking.lost
        self.mapping_iterations += step.mapping_iterations
        self.tracking_time_s += step.tracking_time_s
        self.mapping_time_s += step.mapping_time_s


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
                log.exception("%s %r failed in %s()", self._role, self._name, attr)
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


@contextmanager
def _sigterm_as_interrupt():
    """SIGTERM stops the run like Ctrl-C does, so outputs are written either way."""

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


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
    viewer.start(dataset.camera, out_dir)
    start = time.perf_counter()
    try:
        with _sigterm_as_interrupt(), open(out_dir / "frames.csv", "w", newline="") as frames_log:
            _loop(cfg, dataset, slam, state, csv.writer(frames_log), frames_log, viewer)
            _refine(slam, cfg.refinement_iterations(), state)
        slam.mapper.finish()
        state.completed = True
    except KeyboardInterrupt as exc:
        state.error = f"interrupted ({exc or 'SIGINT'})"
        log.warning("run interrupted after %d frames; writing what it has", len(state.poses))
    except Exception as exc:
        state.error = f"{type(exc).__name__}: {exc}"
        log.error("run failed after %d frames: %s; writing what it has", len(state.poses), state.error)
        raise
    finally:
        try:
            metrics = finish(cfg, slam, dataset, state, time.perf_counter() - start, out_dir)
        finally:
            viewer.close()
    return metrics


def _refine(slam: SLAM, iterations: int, state: RunState) -> None:
    """The map's refinement after the stream: `iterations` more mapping steps, timed apart."""
    if not iterations:
        return
    start = time.perf_counter()
    state.refine_iterations = slam.mapper.optimize(iterations)
    state.refine_time_s = time.perf_counter() - start
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


def write_camera(path: Path, camera, depth_trunc: float) -> None:
    """The run's camera as JSON: width, height (pixels), fx, fy, cx, cy (pixels) and
    depth_trunc (metres, null = none), for tools that render the map later (slamkit-export)."""
    data = {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
            "cy": camera.cy, "depth_trunc": depth_trunc if np.isfinite(depth_trunc) else None}
    _write_json_atomic(path, data)


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


def _loop(cfg: RunConfig, dataset, slam: SLAM, state: RunState, writer, log_file, viewer: ViewerFeed) -> None:
    from tqdm import tqdm

    writer.writerow(["index", "timestamp", "keyframe", "lost", "tracking_ms", "mapping_ms", "iterations",
                     "correspondence_ratio", "num_gaussians", "rss_mb", "note"])
    realtime = cfg.mode is Mode.realtime
    clock = InputClock(cfg.fps_limit if realtime else None)
    mapping = MappingThread(slam.mapper) if realtime else None
    bar = tqdm(total=len(dataset), unit="frame", disable=None if cfg.progress else True, dynamic_ncols=True)
    start = time.perf_counter()
    try:
        if mapping:
            mapping.start()
        skip_errors = cfg.dataset.on_error.value == "skip"
        for frame in prefetched(dataset, cfg.dataset.prefetch, skip_errors):
            if isinstance(frame, UnreadableFrame):
                log.warning("frame %d skipped: %s", frame.index, frame.error)
                state.record_unreadable(frame.timestamp)
                writer.writerow([frame.index, f"{frame.timestamp:.6f}", "none", 1, "", "", 0, "", "", "",
                                 f"unreadable: {frame.error}"])
                bar.update(1)
                continue
            if not state.poses:
                slam.initialize(frame.gt_pose if frame.gt_pose is not None else np.eye(4))
            if clock.wait(frame.index) and cfg.drop_frames and state.poses:
                state.record_dropped(frame)
                writer.writerow([frame.index, f"{frame.timestamp:.6f}", "none", 0, "", "", 0, "", "", "", "dropped"])
                bar.update(1)
                continue
            step = slam.track(frame) if realtime else slam.step(frame)
            if mapping:
                mapping.check()
            state.record(frame, step)
            _log_frame(writer, frame, step, len(slam.gaussian_map))
            viewer.show(frame, step.tracking.pose, step.keyframe, step.tracking.lost)
            bar.update(1)
            every = cfg.eval.running_ate_every
            if every and len(state.poses) % every == 0:
                bar.set_postfix_str(_running_ate(state), refresh=False)
                log_file.flush()
    finally:
        state.stream_time_s = time.perf_counter() - start
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
                     f"{_rss_mb():.1f}", result.stats.get("lost_reason", "")])
    if result.lost:
        log.warning("frame %d lost: %s", frame.index, result.stats.get("lost_reason", "?"))


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.4f}"


def _running_ate(state: RunState) -> str:
    result = evaluation.ate(np.array(state.poses), state.gt_poses)
    return "ATE n/a" if result.rmse_m is None else f"ATE {100 * result.rmse_m:.2f} cm"


def finish(cfg: RunConfig, slam: SLAM, dataset, state: RunState, wall_s: float, out_dir: Path) -> dict[str, Any]:
    """Write trajectory.txt, metrics.json and the plot; return the metrics."""
    n = len(state.poses)
    poses = np.array(state.poses).reshape(n, 4, 4)
    finite = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
    poses[: finite[0] if len(finite) else n] = poses[finite[0]] if len(finite) else np.eye(4)  # unreadable first frames
    write_tum_trajectory(out_dir / "trajectory.txt", state.timestamps, poses)
    write_tum_trajectory(out_dir / "keyframes.txt", [state.timestamps[i] for i in state.keyframe_rows],
                         poses[state.keyframe_rows].reshape(-1, 4, 4))
    has_gt = [i for i, p in enumerate(state.gt_poses) if p is not None and np.all(np.isfinite(p))]
    if has_gt:  # beside the estimate, for evo and slamkit-report
        write_tum_trajectory(out_dir / "groundtruth.txt", [state.timestamps[i] for i in has_gt],
                             np.array([state.gt_poses[i] for i in has_gt]))
    ate = evaluation.ate(poses, state.gt_poses) if n else None
    rpe = evaluation.rpe(poses, state.gt_poses) if n > 1 else None
    metrics: dict[str, Any] = {
        "num_frames": n,
        "num_keyframes": state.num_keyframes,
        "fps": n / wall_s if wall_s > 0 else None,
        "tracking_fps": n / state.tracking_time_s if state.tracking_time_s > 0 else None,
        "stream_fps": n / state.stream_time_s if state.stream_time_s > 0 else None,
        "stream_time_s": state.stream_time_s,
        "tracking_time_s": state.tracking_time_s,
        "mapping_time_s": state.mapping_time_s,
        "wall_time_s": wall_s,
        "mapping_iterations": state.mapping_iterations,
        "refine_iterations": state.refine_iterations,
        "refine_time_s": state.refine_time_s,
        "lost_frames": state.lost_frames,
        "dropped_frames": state.dropped_frames,
        "mode": cfg.mode.value,
        "mapping_threads": torch.get_num_threads(),
        "completed": state.completed,
        "error": state.error,
        "ate_rmse_m": ate.rmse_m if ate else None,
        "ate_mean_m": ate.mean_m if ate else None,
        "ate_frames": ate.num if ate else 0,
        "rpe_trans_rmse_m": rpe["trans_rmse_m"] if rpe else None,
        "rpe_rot_rmse_deg": rpe["rot_rmse_deg"] if rpe else None,
        "num_gaussians": len(slam.gaussian_map),
        "peak_memory_mb": _peak_memory_mb(),
    }
    if state.completed:
        metrics.update(slam.mapper.evaluate(dataset, state.poses, out_dir))
    _write_json_atomic(out_dir / "metrics.json", metrics)
    log.info("%s", summary(metrics))
    if cfg.eval.plot and n:
        from slamkit.formats.plots import plot_trajectory

        has_gt = ate is not None and ate.rmse_m is not None
        est = ate.est_aligned if has_gt else poses[:, :3, 3]
        gt = ate.gt_positions if has_gt else None
        plot_trajectory(out_dir / "trajectory.png", est, gt, title=_summary(metrics))
    return metrics


def _rss_mb() -> float:
    """Current resident memory in MB (Linux /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def _peak_memory_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kilobytes on Linux


def _write_json_atomic(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=float) + "\n")
    os.replace(tmp, path)


def _summary(m: dict[str, Any]) -> str:
    """Frames, ATE and the system's frames/s: the stream's in real-time mode (the frames/s the
    live system kept up with), the whole run's otherwise."""
    ate = "n/a (no ground truth)" if m["ate_rmse_m"] is None else f"{100 * m['ate_rmse_m']:.2f} cm"
    realtime = m.get("mode") == "realtime"
    fps = m["stream_fps"] if realtime else m["fps"]
    fps = f"{fps:.1f} frames/s" + (" in real time" if realtime else "") if fps else "n/a frames/s"
    return f"{m['num_frames']} frames, ATE RMSE {ate}, {fps}"


def summary(m: dict[str, Any]) -> str:
    """One line for the terminal."""
    text = _summary(m) + f", {m['num_keyframes']} keyframes, {m['lost_frames']} lost"
    if m.get("psnr") is not None:
        text += f", PSNR {m['psnr']:.2f} dB"
    if m.get("refine_iterations"):
        text += f" after {m['refine_iterations']} refinement steps ({m['refine_time_s']:.1f} s)"
    return text if m["completed"] else text + " (incomplete)"
