"""What a run has produced so far (`RunState`: poses, keyframes, lost and dropped frames, times,
its status and phase), kept in memory as the stream goes and written out by `slamkit.run.outputs`
even when the run stops early.

A resumed run is made of sessions (one per process: the first run, then each `resume=`). Most
figures are the whole run's, carried by the checkpoint; those that a process measures of itself
(`SESSION_FIGURES`: CPU seconds, peak memory) are kept for this session and summed (the peak:
the largest) with the earlier sessions' (`EarlierSessions`) for the whole run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slamkit.run.lifecycle import Phase
from slamkit.run.loop_closing import Correction
from slamkit.run.slam import StepResult
from slamkit.run.workers import MappingThrottle
from slamkit.types import Frame

#: metrics.json's `status`: what became of the run.
COMPLETED, INTERRUPTED, FAILED, RUNNING = "completed", "interrupted", "failed", "running"
#: The CPU seconds a process counts of itself (RunState fields), summed over a run's sessions.
SESSION_FIGURES = ("tracking_cpu_s", "mapping_cpu_s", "loading_cpu_s", "stream_cpu_s")


@dataclass
class EarlierSessions:
    """What the sessions before this one (a resumed run's) measured of themselves, in all:
    `count` sessions, their CPU seconds (sums; None where one did not record them, e.g. a
    checkpoint written before sessions were counted) and their peak memory (the largest, MB)."""

    count: int = 0
    frames: int = 0
    cpu_s: dict[str, float | None] = field(default_factory=dict)
    peak_memory_mb: float | None = 0.0


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
    delays_s: list[float] = field(default_factory=list)  # each tracked frame's, arrival to pose (this session's)
    mapping_iterations: int = 0
    tracking_time_s: float = 0.0
    mapping_time_s: float = 0.0
    keyframe_handover_s: float = 0.0  # real time: the mapper taking keyframes beside tracking (SLAM.settle)
    keyframe_handover_wait_s: float = 0.0  # real time: the tracking thread waiting for one
    stream_time_s: float = 0.0  # from the first frame to the last one tracked
    # CPU seconds of this process's stream by thread: tracking (the frame loop), mapping (the
    # real-time mapping thread; None in sequential mode, where the loop maps), loading (frames);
    # stream: every thread of the process (the compiled kernels' workers too)
    tracking_cpu_s: float = 0.0
    mapping_cpu_s: float | None = None
    loading_cpu_s: float = 0.0
    stream_cpu_s: float = 0.0
    tracking_cpu_wait_s: float | None = None  # the frame loop runnable but waiting for a CPU (Linux)
    mapping_throttle: MappingThrottle | None = None  # what held real-time mapping back
    refine_iterations: int = 0  # mapping steps after the stream
    refine_time_s: float = 0.0
    slam_time_s: float | None = None  # from the first frame to the end of the refinement
    phase: Phase = Phase.startup  # the phase the run is in (done once completed)
    status: str = RUNNING
    error: str | None = None
    evaluation: dict[str, Any] = field(default_factory=dict)  # the mapper's rendering metrics
    previous_wall_s: float = 0.0  # wall time of the runs this one resumes (slamkit.run.checkpoint)
    earlier: EarlierSessions = field(default_factory=EarlierSessions)  # the sessions this one resumes
    #: a resumed run whose method settings changed: [{frame, before, after}] per change (metrics.json)
    settings_changes: list[dict[str, Any]] = field(default_factory=list)

    @property
    def sessions(self) -> int:
        """Sessions of the run so far, this one included."""
        return self.earlier.count + 1

    def whole_run(self, figure: str) -> float | None:
        """A `SESSION_FIGURES` figure over every session: this one's plus the earlier ones' (None
        where an earlier session's is unknown; mapping_cpu_s None when no session had a mapping
        thread)."""
        mine = getattr(self, figure)
        if self.earlier.count == 0:
            return mine
        if figure not in self.earlier.cpu_s:
            return None
        before = self.earlier.cpu_s[figure]
        return None if before is None and mine is None else (before or 0.0) + (mine or 0.0)

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
        """A frame that arrived while the tracker was busy (real-time mode, realtime.drop_frames): it
        keeps the last pose, so the trajectory still has one line per input frame."""
        self.timestamps.append(frame.timestamp)
        self.poses.append(self.poses[-1])
        self.gt_poses.append(frame.gt_pose)
        self.dropped_frames += 1

    def record(self, frame: Frame, step: StepResult, delay_s: float | None = None) -> None:
        """A tracked frame; `delay_s`: from its arrival to its pose."""
        if delay_s is not None:
            self.delays_s.append(delay_s)
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

    def follow(self, correction: Correction) -> None:
        """A loop closure corrected the keyframes: every pose so far follows its keyframe
        (`Correction.follow`; the keyframes recorded are `keyframe_rows`)."""
        if self.poses:
            self.poses = list(correction.follow(np.array(self.poses), self.keyframe_rows))

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
