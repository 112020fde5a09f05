"""The run's outputs: what a run has produced so far (`RunState`), its metrics, and the files
(`RunOutputs`), each written atomically as soon as what it holds is known, in the order of their
value: camera.json at start-up; trajectory.txt, keyframes.txt, groundtruth.txt, the tracking
metrics (metrics.json) and trajectory.png when the stream ends; the map (the mapper's
`save_map`, map.ply) and the checkpoint (checkpoint.zip) after the refinement, or as the run
stops early; the evaluation merged into metrics.json last.

A file that cannot be written (a full disk) is logged and noted (`RunOutputs.unwritten`), and the
others are still tried: metrics.json is small and is written where space allows."""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from slamkit.formats.atomic import write_atomic
from slamkit.formats.checkpoint import CHECKPOINT_NAME
from slamkit.formats.tum import write_tum_trajectory
from slamkit.metrics import trajectory as evaluation
from slamkit.registry.schema import RunConfig
from slamkit.run.checkpoint import CheckpointWriter
from slamkit.run.lifecycle import Phase, StopSignals
from slamkit.run.slam import SLAM, StepResult
from slamkit.types import Frame

log = logging.getLogger(__name__)

#: metrics.json's `status`: what became of the run.
COMPLETED, INTERRUPTED, FAILED, RUNNING = "completed", "interrupted", "failed", "running"


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
    # CPU seconds of this process's stream by thread: tracking (the frame loop), mapping (the
    # real-time mapping thread; None in sequential mode, where the loop maps), loading (frames);
    # stream: every thread of the process (the compiled kernels' workers too)
    tracking_cpu_s: float = 0.0
    mapping_cpu_s: float | None = None
    loading_cpu_s: float = 0.0
    stream_cpu_s: float = 0.0
    refine_iterations: int = 0  # mapping steps after the stream
    refine_time_s: float = 0.0
    slam_time_s: float | None = None  # from the first frame to the end of the refinement
    phase: Phase = Phase.startup  # the phase the run is in (done once completed)
    status: str = RUNNING
    error: str | None = None
    evaluation: dict[str, Any] = field(default_factory=dict)  # the mapper's rendering metrics
    previous_wall_s: float = 0.0  # wall time of the runs this one resumes (slamkit.run.checkpoint)

    @property
    def completed(self) -> bool:
        return self.status == COMPLETED

    def stop(self, status: str, error: str | None) -> None:
        """The run ends (completed, interrupted or failed) in its current phase; the first
        reason given is kept."""
        if self.status == RUNNING:
            self.status, self.error = status, error
            if status == COMPLETED:
                self.phase = Phase.done

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

    def lost_fraction(self) -> float:
        """Lost frames (tracking lost or unreadable) over the frames the run took in (dropped
        ones excluded); 1.0 when it took in none."""
        taken = len(self.poses) - self.dropped_frames
        return self.lost_frames / taken if taken > 0 else 1.0

    def tracking_failure(self, max_lost_fraction: float) -> str | None:
        """Why the run's trajectory is not a result (no frame tracked, or more than
        `max_lost_fraction` of the frames lost); None when it is."""
        taken = len(self.poses) - self.dropped_frames
        if taken - self.lost_frames <= 0:
            return f"tracking failed: no frame tracked ({self.lost_frames} of {taken} frames lost)"
        if self.lost_fraction() > max_lost_fraction:
            return (f"tracking failed: {self.lost_frames} of {taken} frames lost, more than "
                    f"eval.max_lost_fraction={max_lost_fraction:g}")
        return None

    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses; the unreadable first frames take the first pose."""
        n = len(self.poses)
        poses = np.array(self.poses).reshape(n, 4, 4)
        finite = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
        poses[: finite[0] if len(finite) else n] = poses[finite[0]] if len(finite) else np.eye(4)
        return poses


def write_camera(path: Path, camera, depth_trunc: float) -> None:
    """The run's camera as JSON: width, height (pixels), fx, fy, cx, cy (pixels) and
    depth_trunc (metres, null = none), for tools that render the map later (slamkit-export)."""
    data = {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
            "cy": camera.cy, "depth_trunc": depth_trunc if np.isfinite(depth_trunc) else None}
    _write_json_atomic(path, data)


class RunOutputs:
    """The files of one run in `out_dir` (see the module docstring). `kept` lists the files
    written, `unwritten` the ones that could not be (name -> why). With `checkpoints`, the map's
    save also writes the run's checkpoint (`slamkit.run.checkpoint`); `stop` says whether a
    signal cut a step in half (then no checkpoint is written from that state)."""

    def __init__(self, cfg: RunConfig, slam: SLAM, state: RunState, out_dir: Path,
                 checkpoints: CheckpointWriter | None = None, stop: StopSignals | None = None):
        self.cfg, self.slam, self.state, self.out_dir = cfg, slam, state, out_dir
        self.checkpoints, self.stop = checkpoints, stop
        self.kept: list[str] = []
        self.unwritten: dict[str, str] = {}
        self.start = time.perf_counter()  # the first frame's
        self.trajectory_saved = self.map_saved = False

    def keep(self, name: str, write: Callable[[], Any]) -> bool:
        """Run `write` (which writes `name`). An OSError (a full disk, a read-only folder) is
        logged and noted in `unwritten`; it is raised while the run is going (the run stops
        and keeps what it can), not once it is stopping (the other files are still tried)."""
        try:
            write()
        except OSError as exc:
            self._unwritten(name, exc)
            if self.state.status == RUNNING:
                raise
            return False
        if name not in self.kept:
            self.kept.append(name)
        return True

    def save_camera(self, camera, depth_trunc: float) -> None:
        self.keep("camera.json", lambda: write_camera(self.out_dir / "camera.json", camera, depth_trunc))

    def save_trajectory(self) -> None:
        """When the stream ends: trajectory.txt, keyframes.txt, groundtruth.txt, the tracking
        metrics (metrics.json) and trajectory.png."""
        state, out = self.state, self.out_dir
        self.trajectory_saved = True
        poses = state.trajectory()
        self.keep("trajectory.txt", lambda: write_tum_trajectory(out / "trajectory.txt", state.timestamps, poses))
        rows = state.keyframe_rows
        self.keep("keyframes.txt", lambda: write_tum_trajectory(out / "keyframes.txt", [state.timestamps[i] for i in rows],
                                                                 poses[rows].reshape(-1, 4, 4)))
        has_gt = [i for i, p in enumerate(state.gt_poses) if p is not None and np.all(np.isfinite(p))]
        if has_gt:  # beside the estimate, for evo and slamkit-report
            self.keep("groundtruth.txt", lambda: write_tum_trajectory(
                out / "groundtruth.txt", [state.timestamps[i] for i in has_gt], np.array([state.gt_poses[i] for i in has_gt])))
        metrics = self.save_metrics()
        if self.cfg.eval.plot and len(poses):
            self.keep("trajectory.png", lambda: self._plot(poses, metrics))

    def save_map(self) -> None:
        """The map trained so far (the mapper's `save_map`: map.ply), once the mapper has stopped
        changing it, then the checkpoint: the run's one place for what it keeps of its map. A run
        already stopping (interrupted twice, failed) logs a map it cannot write instead of raising."""
        self.map_saved = True
        self._save_map_ply()
        self._save_checkpoint()

    def _save_map_ply(self) -> None:
        try:
            written = self.slam.mapper.save_map(self.out_dir) or []
        except OSError as exc:
            self._unwritten(Path(exc.filename).name if exc.filename else "map.ply", exc)
            if self.state.status == RUNNING:
                raise
            return
        except Exception as exc:
            if self.state.status == RUNNING:
                raise
            log.error("the map could not be written: %s: %s", type(exc).__name__, exc)
            return
        self.kept += [Path(p).name for p in written]

    def _save_checkpoint(self) -> None:
        """checkpoint.zip: `end` after the refinement, `interrupted` when a signal stopped the run
        at a safe point. None from a failed run, nor from a state a second signal cut in half (the
        last checkpoint written, every N keyframes, stays)."""
        status = self.state.status
        if self.checkpoints is None or status == FAILED:
            return
        if self.stop is not None and self.stop.cut_short:
            log.warning("no checkpoint from this state: a second signal stopped the run in the middle of a step")
            return
        try:
            path = self.checkpoints.save("end" if status == RUNNING else "interrupted")
        except OSError as exc:
            self._unwritten(Path(exc.filename).name if exc.filename else CHECKPOINT_NAME, exc)
            if status == RUNNING:
                raise
            return
        if path is not None and path.name not in self.kept:
            self.kept.append(path.name)

    def save_metrics(self) -> dict[str, Any]:
        """metrics.json as the run stands; returns the metrics."""
        metrics = run_metrics(self.cfg, self.slam, self.state, time.perf_counter() - self.start)
        self.keep("metrics.json", lambda: _write_json_atomic(self.out_dir / "metrics.json", metrics))
        return metrics

    def save_all(self) -> dict[str, Any]:
        """What the run has not written yet (its trajectory, its map), then metrics.json as it
        ends; returns the metrics."""
        if not self.trajectory_saved:
            self.save_trajectory()
        if not self.map_saved:
            self.save_map()
        return self.save_metrics()

    def _unwritten(self, name: str, exc: OSError) -> None:
        self.unwritten[name] = exc.strerror or str(exc)
        log.error("could not write %s: %s", self.out_dir / name, self.unwritten[name])

    def _plot(self, poses: np.ndarray, metrics: dict[str, Any]) -> None:
        from slamkit.formats.plots import plot_trajectory

        ate = evaluation.ate(poses, self.state.gt_poses)
        has_gt = ate.rmse_m is not None
        plot_trajectory(self.out_dir / "trajectory.png", ate.est_aligned if has_gt else poses[:, :3, 3],
                        ate.gt_positions if has_gt else None, title=_summary(metrics))


def run_metrics(cfg: RunConfig, slam: SLAM, state: RunState, wall_s: float) -> dict[str, Any]:
    """metrics.json's content for the run as it stands (`wall_s`: seconds since its first frame;
    a resumed run adds the wall time of the runs before it).
    A run whose tracking failed presents no trajectory error (ate_*, rpe_* null)."""
    n = len(state.poses)
    poses = state.trajectory()
    failure = state.tracking_failure(cfg.eval.max_lost_fraction) if n else None
    ate = evaluation.ate(poses, state.gt_poses) if n and not failure else None
    rpe = evaluation.rpe(poses, state.gt_poses) if n > 1 and not failure else None
    slam_s = (state.slam_time_s if state.slam_time_s is not None else wall_s) + state.previous_wall_s
    metrics: dict[str, Any] = {
        "num_frames": n,
        "num_keyframes": state.num_keyframes,
        "fps": n / slam_s if slam_s > 0 else None,
        "tracking_fps": n / state.tracking_time_s if state.tracking_time_s > 0 else None,
        "stream_fps": n / state.stream_time_s if state.stream_time_s > 0 else None,
        "stream_time_s": state.stream_time_s,
        "tracking_time_s": state.tracking_time_s,
        "mapping_time_s": state.mapping_time_s,
        "tracking_cpu_s": state.tracking_cpu_s,
        "mapping_cpu_s": state.mapping_cpu_s,
        "loading_cpu_s": state.loading_cpu_s,
        "stream_cpu_s": state.stream_cpu_s,
        "wall_time_s": slam_s,
        "mapping_iterations": state.mapping_iterations,
        "refine_iterations": state.refine_iterations,
        "refine_time_s": state.refine_time_s,
        "lost_frames": state.lost_frames,
        "lost_fraction": state.lost_fraction() if n else None,
        "tracking_failure": failure,  # why no trajectory error is reported
        "dropped_frames": state.dropped_frames,
        "mode": cfg.mode.value,
        "mapping_threads": torch.get_num_threads(),
        "completed": state.completed,
        "status": state.status,
        "phase": state.phase.value,
        "error": state.error,
        "ate_rmse_m": ate.rmse_m if ate else None,
        "ate_mean_m": ate.mean_m if ate else None,
        "ate_frames": ate.num if ate else 0,
        "rpe_trans_rmse_m": rpe["trans_rmse_m"] if rpe else None,
        "rpe_rot_rmse_deg": rpe["rot_rmse_deg"] if rpe else None,
        "num_gaussians": len(slam.gaussian_map),
    }
    metrics.update(state.evaluation)
    metrics["peak_memory_mb"] = _peak_memory_mb()  # so far: after the evaluation in the last write
    return metrics


def rss_mb() -> float:
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
    write_atomic(path, json.dumps(data, indent=2, default=float) + "\n")


def _summary(m: dict[str, Any]) -> str:
    """Frames, ATE and the system's frames/s: the stream's in real-time mode (the frames/s the
    live system kept up with), the whole run's otherwise."""
    if m["ate_rmse_m"] is not None:
        ate = f"{100 * m['ate_rmse_m']:.2f} cm"
    elif m.get("tracking_failure"):
        ate = "not reported"
    else:
        ate = "n/a (no frames)" if not m["num_frames"] else "n/a (no ground truth)"
    realtime = m.get("mode") == "realtime"
    fps = m["stream_fps"] if realtime else m["fps"]
    fps = f"{fps:.1f} frames/s" + (" in real time" if realtime else "") if fps else "n/a frames/s"
    return f"{m['num_frames']} frames, ATE RMSE {ate}, {fps}"


def summary(m: dict[str, Any]) -> str:
    """One line for the terminal: the result, or why there is none."""
    text = _summary(m) + f", {m['num_keyframes']} keyframes, {m['lost_frames']} lost"
    if m.get("psnr") is not None:
        text += f", PSNR {m['psnr']:.2f} dB"
    if m.get("refine_iterations"):
        text += f" after {m['refine_iterations']} refinement steps ({m['refine_time_s']:.1f} s)"
    status = m.get("status", COMPLETED if m["completed"] else INTERRUPTED)
    if status == COMPLETED:
        return text
    if status == INTERRUPTED:
        return text + f" (incomplete: interrupted during {m.get('phase', '?')})"
    return text + f" (failed: {m.get('error')})"


def _index_below(cell: str, index: int) -> bool:
    return cell.isdigit() and int(cell) < index


class FrameLog:
    """frames.csv: one row per input frame (keyframe kind, lost flag and reason, tracking and
    mapping time in ms, ...), appended as the stream goes and flushed every `flush` call and at
    the end. A log, not written atomically: after a kill its last row may be cut short; a reader
    drops a last line that has no line end. An OSError names the file."""

    COLUMNS = ["index", "timestamp", "keyframe", "lost", "tracking_ms", "mapping_ms", "iterations",
               "correspondence_ratio", "num_gaussians", "rss_mb", "note"]

    def __init__(self, path: Path, resume_from: int = 0):
        """`resume_from` > 0: extend the log of the run this one resumes, from that frame index
        on; the rows it had logged from there (after its checkpoint, before it was killed) and
        a last row cut short are dropped first, so that every frame has one row."""
        self.path = path
        append = resume_from > 0 and path.exists()
        if append:
            self._guard(self._keep_rows_before, resume_from)
        self._file = self._guard(open, path, "a" if append else "w", newline="")
        self._writer = csv.writer(self._file)
        if not append:
            self._row(self.COLUMNS)

    def _keep_rows_before(self, index: int) -> None:
        with open(self.path, newline="") as f:
            text = f.read()
        text = text[: text.rfind("\n") + 1]  # (a row cut short has no line end)
        rows = list(csv.reader(io.StringIO(text)))[1:]
        out = io.StringIO()
        csv.writer(out).writerows([self.COLUMNS] + [row for row in rows if row and _index_below(row[0], index)])
        write_atomic(self.path, out.getvalue())

    def frame(self, frame: Frame, step: StepResult, num_gaussians: int) -> None:
        result = step.tracking
        self._row([frame.index, f"{frame.timestamp:.6f}", step.keyframe.value, int(result.lost),
                   f"{1e3 * step.tracking_time_s:.2f}", f"{1e3 * step.mapping_time_s:.2f}", step.mapping_iterations,
                   _fmt(result.correspondence_ratio), num_gaussians, f"{rss_mb():.1f}",
                   result.stats.get("lost_reason", "")])

    def unreadable(self, index: int, timestamp: float, error: Exception) -> None:
        self._row([index, f"{timestamp:.6f}", "none", 1, "", "", 0, "", "", "", f"unreadable: {error}"])

    def dropped(self, frame: Frame) -> None:
        self._row([frame.index, f"{frame.timestamp:.6f}", "none", 0, "", "", 0, "", "", "", "dropped"])

    def flush(self) -> None:
        self._guard(self._file.flush)

    def close(self) -> None:
        self._guard(self._file.close)

    def __enter__(self) -> "FrameLog":
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.close()
        except OSError:
            if exc[0] is None:  # an error already on its way says what went wrong first
                raise

    def _row(self, cells: list) -> None:
        self._guard(self._writer.writerow, cells)

    def _guard(self, call, *args, **kwargs):
        try:
            return call(*args, **kwargs)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc), str(self.path)) from exc


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.4f}"
