"""metrics.json's content for a run as it stands (`run_metrics`), the one-line summary the
terminal prints (`summary`), and the process's memory figures they report.

Every figure covers the whole run, over all its sessions (a resumed run's: `sessions`), but
those named in `last_session_only` (the process's thread setting, the mapper's per-phase step
times, the real-time keyframe handovers beside tracking); `session` gives the last session's
own figures (its frames, wall time, CPU seconds, peak memory). Where no ATE is reported,
`ate_unavailable` says why.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from slamkit.metrics import trajectory as evaluation
from slamkit.metrics.trajectory import MIN_ATE_POSES
from slamkit.registry.schema import RunConfig
from slamkit.run.settings import method_settings
from slamkit.run.slam import SLAM
from slamkit.run.state import COMPLETED, INTERRUPTED, SESSION_FIGURES, RunState

#: metrics.json's figures that cover the last session only (`last_session_only`).
LAST_SESSION_ONLY = ("mapping_threads", "mapping_step_ms", "keyframe_handover_s",
                     "keyframe_handover_wait_s", "delay_median_ms", "delay_p99_ms", "delay_max_ms")


def run_metrics(cfg: RunConfig, slam: SLAM, state: RunState, wall_s: float) -> dict[str, Any]:
    """metrics.json's content for the run as it stands (`wall_s`: seconds since its first frame;
    a resumed run adds the wall time of the runs before it).
    A run whose tracking failed presents no trajectory error (ate_*, rpe_* null)."""
    n = len(state.poses)
    poses = state.trajectory()
    failure = state.tracking_failure(cfg.eval.max_lost_fraction) if n else None
    ate = evaluation.ate(poses, state.gt_poses) if n and not failure else None
    rpe = evaluation.rpe(poses, state.gt_poses) if n > 1 and not failure else None
    session_s = state.slam_time_s if state.slam_time_s is not None else wall_s
    slam_s = session_s + state.previous_wall_s
    metrics: dict[str, Any] = {
        "num_frames": n,
        "num_keyframes": state.num_keyframes,
        "fps": n / slam_s if slam_s > 0 else None,
        "tracking_fps": n / state.tracking_time_s if state.tracking_time_s > 0 else None,
        "stream_fps": n / state.stream_time_s if state.stream_time_s > 0 else None,
        "stream_time_s": state.stream_time_s,
        "tracking_time_s": state.tracking_time_s,
        "mapping_time_s": state.mapping_time_s,
        "keyframe_handover_s": state.keyframe_handover_s,  # real time: the mapper taking keyframes beside tracking
        "keyframe_handover_wait_s": state.keyframe_handover_wait_s,  # the tracking thread waiting for it
        **{figure: state.whole_run(figure) for figure in SESSION_FIGURES},
        "tracking_cpu_wait_s": state.tracking_cpu_wait_s,  # this session's, as the throttle's
        **_throttle(state),
        "wall_time_s": slam_s,
        "mapping_iterations": state.mapping_iterations,
        "refine_iterations": state.refine_iterations,
        "refine_time_s": state.refine_time_s,
        "lost_frames": state.lost_frames,
        "lost_fraction": state.lost_fraction() if n else None,
        "tracking_failure": failure,  # why no trajectory error is reported
        "dropped_frames": state.dropped_frames,
        **_delays(state.delays_s),
        "mode": cfg.mode.value,
        "mapping_threads": torch.get_num_threads(),
        "completed": state.completed,
        "status": state.status,
        "phase": state.phase.value,
        "error": state.error,
        "ate_unavailable": _ate_unavailable(n, failure, ate),
        "ate_rmse_m": ate.rmse_m if ate else None,
        "ate_mean_m": ate.mean_m if ate else None,
        "ate_frames": ate.num if ate else 0,
        "rpe_trans_rmse_m": rpe["trans_rmse_m"] if rpe else None,
        "rpe_rot_rmse_deg": rpe["rot_rmse_deg"] if rpe else None,
        "num_gaussians": len(slam.gaussian_map),
        "settings": method_settings(cfg, slam.boundary.names),  # the method as run, the defaults filled
    }
    if state.settings_changes:  # a resumed run that changed them: the frame from which `settings` hold
        metrics["settings_changes"] = state.settings_changes
    metrics.update(state.evaluation)
    peak = peak_memory_mb()  # so far: after the evaluation in the last write
    earlier_peak = state.earlier.peak_memory_mb
    metrics["peak_memory_mb"] = None if earlier_peak is None and state.earlier.count else max(peak, earlier_peak or 0)
    metrics["sessions"] = state.sessions
    metrics["session"] = {"num_frames": n - state.earlier.frames, "wall_time_s": session_s,
                          **{figure: getattr(state, figure) for figure in SESSION_FIGURES}, "peak_memory_mb": peak}
    metrics["last_session_only"] = list(LAST_SESSION_ONLY)
    return metrics


def _delays(delays_s: list[float]) -> dict[str, float | None]:
    """The median, 99th percentile and largest delay of this session's tracked frames, from
    arrival to pose, in ms (a live camera does not wait: the slowest frames matter)."""
    if not delays_s:
        return {"delay_median_ms": None, "delay_p99_ms": None, "delay_max_ms": None}
    ms = 1e3 * np.asarray(delays_s)
    return {"delay_median_ms": float(np.median(ms)), "delay_p99_ms": float(np.percentile(ms, 99)),
            "delay_max_ms": float(ms.max())}


def _throttle(state: RunState) -> dict[str, Any]:
    """The real-time mapping thread's priority and what held it back (None in sequential mode)."""
    t = state.mapping_throttle
    return {"mapping_priority": t and t.priority, "mapping_cpu_wait_s": t and t.cpu_wait_s,
            "mapping_no_keyframe_s": t and t.no_keyframe_s, "mapping_blocked_s": t and t.blocked_s,
            "mapping_yielded_s": t and t.yielded_s}


def _ate_unavailable(frames: int, failure: str | None, ate) -> str | None:
    """Why no ATE is reported (None when one is)."""
    if ate is not None and ate.rmse_m is not None:
        return None
    if failure:
        return failure
    if not frames:
        return "no frames"
    if ate is None or ate.num == 0:
        return "no ground truth"
    return f"too few frames: {ate.num} with ground truth, the ATE needs {MIN_ATE_POSES}"


def folder_mb(folder: Path) -> float:
    """The size of the files under `folder`, MB (the run folder's, for the summary line)."""
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file() and not p.is_symlink()) / 2**20


def rss_mb() -> float:
    """Current resident memory in MB (Linux /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def peak_memory_mb() -> float:
    """This process's peak resident memory so far, MB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kilobytes on Linux


def rates(m: dict[str, Any]) -> tuple[str, str | None]:
    """The system's frames/s, named: first the one the run is judged by (the stream's in
    real-time mode: the rate the live system kept up with; the whole run's otherwise), then the
    other (None where it is not known)."""
    def rate(fps: float | None, what: str) -> str | None:
        return f"{fps:.1f} frames/s {what}" if fps else None

    stream, whole = m.get("stream_fps"), m.get("fps")
    if m.get("mode") == "realtime":
        return rate(stream, "in real time (stream)") or "n/a frames/s (stream)", rate(whole, "(whole run)")
    return rate(whole, "(whole run)") or "n/a frames/s (whole run)", rate(stream, "(stream)")


def headline(m: dict[str, Any], stream_rate: bool = False) -> str:
    """Frames, ATE and the system's frames/s, named (`rates`); with `stream_rate`, the stream's
    (trajectory.png's title: the plot is drawn when the stream ends, before the whole run's rate
    is known)."""
    if m["ate_rmse_m"] is not None:
        ate = f"{100 * m['ate_rmse_m']:.2f} cm"
    elif m.get("tracking_failure"):
        ate = "not reported"
    elif m.get("ate_unavailable"):
        ate = f"n/a ({m['ate_unavailable']})"
    else:  # metrics written before ate_unavailable
        ate = "n/a (no frames)" if not m["num_frames"] else "n/a (no ground truth)"
    if stream_rate:
        fps = m.get("stream_fps")
        rate = f"{fps:.1f} frames/s (stream)" if fps else "n/a frames/s (stream)"
    else:
        rate = rates(m)[0]
    return f"{m['num_frames']} frames, ATE RMSE {ate}, {rate}"


def summary(m: dict[str, Any]) -> str:
    """One line for the terminal: what the run did (frames, ATE, both frames/s named, keyframes,
    lost frames, loops closed, mapping steps, PSNR, the run folder's size), or why there is no
    result."""
    other = rates(m)[1]
    text = headline(m) + (f", {other}" if other else "")
    text += f", {m['num_keyframes']} keyframes, {m['lost_frames']} lost"
    if m.get("loops_accepted") is not None:  # loop closure on
        text += f", {m['loops_accepted']} loops closed"
    if m.get("mapping_priority"):  # real time: the steps mapping got beside tracking, and what held it back
        waited = m.get("mapping_cpu_wait_s")
        text += (f", {m['mapping_iterations']} mapping steps in the stream ({m['mapping_priority']} priority"
                 + ("" if waited is None else f", {waited:.1f} s waiting for a CPU") + ")")
    elif m.get("mapping_iterations"):
        text += f", {m['mapping_iterations']} mapping steps in the stream"
    if m.get("refine_iterations"):
        text += f", {m['refine_iterations']} refinement steps after it ({m['refine_time_s']:.1f} s)"
    if m.get("psnr") is not None:
        text += f", PSNR {m['psnr']:.2f} dB"
    if m.get("run_folder_mb") is not None:
        text += f", run folder {m['run_folder_mb']:.1f} MB"
    status = m.get("status", COMPLETED if m["completed"] else INTERRUPTED)
    if status == COMPLETED:
        return text
    if status == INTERRUPTED:
        return text + f" (incomplete: interrupted during {m.get('phase', '?')})"
    return text + f" (failed: {m.get('error')})"
