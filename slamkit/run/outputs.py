"""The run's outputs: what a run has produced so far (`RunState`), and writing it out
(trajectory.txt, keyframes.txt, groundtruth.txt, camera.json, metrics.json, trajectory.png) with
the one-line summary. Written atomically, also for a run that stopped early."""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from slamkit.formats.atomic import write_atomic
from slamkit.formats.tum import write_tum_trajectory
from slamkit.metrics import trajectory as evaluation
from slamkit.registry.schema import RunConfig
from slamkit.run.slam import SLAM, StepResult
from slamkit.types import Frame

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
    previous_wall_s: float = 0.0  # wall time of the runs this one resumes (slamkit.run.checkpoint)

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


def write_camera(path: Path, camera, depth_trunc: float) -> None:
    """The run's camera as JSON: width, height (pixels), fx, fy, cx, cy (pixels) and
    depth_trunc (metres, null = none), for tools that render the map later (slamkit-export)."""
    data = {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
            "cy": camera.cy, "depth_trunc": depth_trunc if np.isfinite(depth_trunc) else None}
    _write_json_atomic(path, data)


def write_outputs(cfg: RunConfig, slam: SLAM, dataset, state: RunState, wall_s: float, out_dir: Path) -> dict[str, Any]:
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
        "fps": n / (wall_s + state.previous_wall_s) if wall_s > 0 else None,
        "tracking_fps": n / state.tracking_time_s if state.tracking_time_s > 0 else None,
        "stream_fps": n / state.stream_time_s if state.stream_time_s > 0 else None,
        "stream_time_s": state.stream_time_s,
        "tracking_time_s": state.tracking_time_s,
        "mapping_time_s": state.mapping_time_s,
        "wall_time_s": wall_s + state.previous_wall_s,
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
