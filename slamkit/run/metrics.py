"""metrics.json's content for a run as it stands (`run_metrics`), the one-line summary the
terminal prints (`summary`), and the process's memory figures they report."""

from __future__ import annotations

import os
from typing import Any

import torch

from slamkit.metrics import trajectory as evaluation
from slamkit.registry.schema import RunConfig
from slamkit.run.settings import method_settings
from slamkit.run.slam import SLAM
from slamkit.run.state import COMPLETED, INTERRUPTED, RunState


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
        "settings": method_settings(cfg),  # the method as run, the preset's and the mode's defaults filled
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


def headline(m: dict[str, Any]) -> str:
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
    text = headline(m) + f", {m['num_keyframes']} keyframes, {m['lost_frames']} lost"
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
