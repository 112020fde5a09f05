"""KISS-ICP baseline (Vizzo et al., RA-L 2023) through kiss-icp's Python API.

The frame's depth is back-projected densely (every `pixel_stride`-th pixel) and KISS-ICP's own
voxel grid downsamples it: fed a sparse cloud (every 10th pixel of Replica) its adaptive
threshold stays at its 2 m initial value and it drifts, so the baseline gets a dense cloud.
KISS-ICP keeps its own voxel map; the shared GaussianMap is not used.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP

from slamkit.geometry.transforms import backproject, invert_pose
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, RunContext, Tracker, require
from slamkit.types import Frame, TrackingResult


@dataclass
class KissICPConfig(PluginConfig):
    """Options of `tracker=kiss_icp`, with defaults for indoor RGB-D (a few metres, millimetre noise)."""

    #: back-project every n-th pixel in x and y (dense: KISS-ICP voxelises itself)
    pixel_stride: int = 2
    #: metres, KISS-ICP's map voxel (it registers on a 1.5x coarser grid)
    voxel_size: float = 0.05
    #: metres; farther points are not used (null: the dataset's depth_trunc, at most 100)
    max_range: float | None = None
    #: metres; nearer points are not used
    min_range: float = 0.1
    #: metres, the adaptive correspondence threshold before motion is seen (KISS-ICP's LiDAR default: 2)
    initial_threshold: float = 0.1
    #: metres; a smaller motion does not update the adaptive threshold
    min_motion: float = 0.005
    #: map points kept per voxel
    max_points_per_voxel: int = 20
    #: fewer valid depth points: the frame is lost
    min_points: int = 100

    def validate(self) -> None:
        require(self.pixel_stride >= 1, "tracker.pixel_stride", "an integer >= 1", self.pixel_stride)
        require(self.voxel_size > 0, "tracker.voxel_size", "> 0 metres", self.voxel_size)
        require(self.initial_threshold > 0, "tracker.initial_threshold", "> 0 metres", self.initial_threshold)
        require(self.min_range >= 0, "tracker.min_range", ">= 0 metres", self.min_range)
        require(self.max_range is None or self.max_range > self.min_range, "tracker.max_range",
                f"null or > tracker.min_range ({self.min_range} metres)", self.max_range)
        require(self.min_motion >= 0, "tracker.min_motion", ">= 0 metres", self.min_motion)
        require(self.max_points_per_voxel >= 1, "tracker.max_points_per_voxel", "an integer >= 1",
                self.max_points_per_voxel)
        require(self.min_points >= 1, "tracker.min_points", "an integer >= 1", self.min_points)


class KissICPTracker(Tracker):
    """Point-to-point ICP on KISS-ICP's adaptive voxel map (frame-to-local-map)."""

    def __init__(self, cfg: KissICPConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        self.first_pose = np.eye(4)
        self.odometry: KissICP | None = None

    def initialize(self, first_pose: np.ndarray) -> None:
        self.first_pose = first_pose.copy()

    def _make_odometry(self, frame: Frame) -> KissICP:
        c = self.cfg
        kiss = KISSConfig()
        kiss.data.deskew = False
        kiss.data.max_range = c.max_range if c.max_range is not None else min(frame.depth_trunc, 100.0)
        kiss.data.min_range = c.min_range
        kiss.mapping.voxel_size = c.voxel_size
        kiss.mapping.max_points_per_voxel = c.max_points_per_voxel
        kiss.adaptive_threshold.initial_threshold = c.initial_threshold
        kiss.adaptive_threshold.min_motion_th = c.min_motion
        return KissICP(kiss)

    def track(self, frame: Frame) -> TrackingResult:
        if self.odometry is None:
            self.odometry = self._make_odometry(frame)
        start = time.perf_counter()
        points, _ = backproject(frame.depth, frame.camera, self.cfg.pixel_stride)
        predicted = self.odometry.last_pose @ self.odometry.last_delta
        if len(points) < self.cfg.min_points:
            return self._lost(predicted, f"{len(points)} valid depth points < {self.cfg.min_points}")
        self.odometry.register_frame(points.astype(np.float64), np.zeros(len(points)))
        pose = self.odometry.last_pose
        if not np.all(np.isfinite(pose)):
            return self._lost(predicted, "non-finite pose")
        stats = {"points": len(points), "register_s": time.perf_counter() - start}
        return TrackingResult(pose=self.first_pose @ pose, stats=stats)

    def _lost(self, predicted_local: np.ndarray, reason: str) -> TrackingResult:
        # Keep KISS-ICP's motion model consistent with the pose we report.
        self.odometry.last_delta = invert_pose(self.odometry.last_pose) @ predicted_local
        self.odometry.last_pose = predicted_local
        return TrackingResult(pose=self.first_pose @ predicted_local, lost=True, stats={"lost_reason": reason})


@hookimpl
def slamkit_plugins():
    return [PluginSpec("kiss_icp", KissICPTracker, KissICPConfig)]
