"""small_gicp's GICP (Koide, 2024) as an external anchor: frame-to-model tracking on a voxelised
model with small_gicp's own covariances (k nearest neighbours), constant-velocity initial guess.

The model is the union of keyframe clouds in world coordinates, voxel-downsampled; a frame becomes
a keyframe when it moved more than `keyframe_translation` or `keyframe_rotation_deg` since the
last one, and the model (covariances, KD-tree) is rebuilt then only. small_gicp is an optional
dependency (`pip install small-gicp`, in the `test` and `bench` extras).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from slamkit.errors import ConfigError
from slamkit.geometry.transforms import (
    backproject,
    invert_pose,
    make_pose,
    nearest_rotation,
    rotation_angle_deg,
    transform_points,
)
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, RunContext, Tracker, require, thread_count
from slamkit.types import Frame, TrackingResult


@dataclass
class SmallGICPConfig(PluginConfig):
    """Options of `tracker=small_gicp`, frame-to-model GICP with small_gicp."""

    #: back-project every n-th pixel in x and y
    pixel_stride: int = 2
    #: metres, the voxel that downsamples the frame and the model
    voxel_size: float = 0.02
    #: metres
    max_correspondence_distance: float = 0.05
    #: neighbours of each point's covariance
    knn: int = 10
    #: GICP iterations per frame, at most
    max_iterations: int = 20
    #: metres moved since the last keyframe that make the frame a keyframe (added to the model)
    keyframe_translation: float = 0.05
    #: degrees turned since the last keyframe that make the frame a keyframe
    keyframe_rotation_deg: float = 5.0
    #: metres; farther points are not used (null: the dataset's depth_trunc)
    max_range: float | None = None
    #: small_gicp's threads
    num_threads: int = thread_count(2)
    #: fewer valid depth points: the frame is lost
    min_points: int = 100

    def validate(self) -> None:
        require(self.pixel_stride >= 1, "tracker.pixel_stride", "an integer >= 1", self.pixel_stride)
        require(self.voxel_size > 0, "tracker.voxel_size", "> 0 metres", self.voxel_size)
        require(self.max_correspondence_distance > 0, "tracker.max_correspondence_distance", "> 0 metres",
                self.max_correspondence_distance)
        require(self.knn >= 3, "tracker.knn", "an integer >= 3", self.knn)
        require(self.num_threads >= 1, "tracker.num_threads", "an integer >= 1", self.num_threads)
        require(self.max_iterations >= 1, "tracker.max_iterations", "an integer >= 1", self.max_iterations)
        require(self.keyframe_translation >= 0, "tracker.keyframe_translation", ">= 0 metres",
                self.keyframe_translation)
        require(self.keyframe_rotation_deg >= 0, "tracker.keyframe_rotation_deg", ">= 0 degrees",
                self.keyframe_rotation_deg)
        require(self.max_range is None or self.max_range > 0, "tracker.max_range", "null or > 0 metres", self.max_range)
        require(self.min_points >= 1, "tracker.min_points", "an integer >= 1", self.min_points)


class SmallGICPTracker(Tracker):
    def __init__(self, cfg: SmallGICPConfig, context: RunContext = RunContext()):
        try:
            import small_gicp
        except ImportError as exc:
            raise ConfigError("tracker small_gicp needs the small-gicp package (pip install small-gicp)") from exc
        self.sg = small_gicp
        self.cfg = cfg
        self.pose = np.eye(4)
        self.velocity = np.eye(4)  # last relative motion, camera-to-camera
        self.model_points = np.zeros((0, 3))
        self.model = None  # (PointCloud, KdTree)
        self.last_keyframe: np.ndarray | None = None

    def initialize(self, first_pose: np.ndarray) -> None:
        self.pose = first_pose.copy()

    def track(self, frame: Frame) -> TrackingResult:
        start = time.perf_counter()
        points, _ = backproject(frame.depth, frame.camera, self.cfg.pixel_stride)
        max_range = self.cfg.max_range or frame.depth_trunc
        points = points[points[:, 2] <= max_range].astype(np.float64)
        predicted = self.pose @ self.velocity
        if len(points) < self.cfg.min_points:
            return self._finish(predicted, start, lost=f"{len(points)} valid depth points < {self.cfg.min_points}")
        source, _ = self.sg.preprocess_points(points, self.cfg.voxel_size, self.cfg.knn, self.cfg.num_threads)
        if self.model is None:
            return self._finish(predicted, start, keyframe_points=points)
        result = self.sg.align(self.model[0], source, self.model[1], init_T_target_source=predicted,
                               registration_type="GICP",
                               max_correspondence_distance=self.cfg.max_correspondence_distance,
                               num_threads=self.cfg.num_threads, max_iterations=self.cfg.max_iterations)
        T = np.asarray(result.T_target_source)
        pose = make_pose(nearest_rotation(T[:3, :3]), T[:3, 3])  # copies; re-orthonormalised
        if not np.all(np.isfinite(pose)) or result.num_inliers < 50:
            return self._finish(predicted, start, lost=f"alignment failed ({result.num_inliers} inliers)")
        return self._finish(pose, start, keyframe_points=points)

    def _finish(self, pose, start, lost: str | None = None, keyframe_points=None) -> TrackingResult:
        self.velocity = invert_pose(self.pose) @ pose
        self.pose = pose
        if keyframe_points is not None and self._is_keyframe(pose):
            self._add_to_model(keyframe_points, pose)
        stats = {"register_s": time.perf_counter() - start}
        if lost:
            stats["lost_reason"] = lost
        return TrackingResult(pose=pose.copy(), lost=lost is not None, stats=stats)

    def _is_keyframe(self, pose: np.ndarray) -> bool:
        if self.last_keyframe is None:
            return True
        delta = invert_pose(self.last_keyframe) @ pose
        return (np.linalg.norm(delta[:3, 3]) > self.cfg.keyframe_translation
                or rotation_angle_deg(delta[:3, :3]) > self.cfg.keyframe_rotation_deg)

    def _add_to_model(self, points: np.ndarray, pose: np.ndarray) -> None:
        world = np.concatenate([self.model_points, transform_points(pose, points)])
        cloud = self.sg.voxelgrid_sampling(world, self.cfg.voxel_size, self.cfg.num_threads)
        self.model_points = np.array(cloud.points()[:, :3], dtype=np.float64)
        self.model = self.sg.preprocess_points(self.model_points, self.cfg.voxel_size, self.cfg.knn,
                                               self.cfg.num_threads)
        self.last_keyframe = pose.copy()


@hookimpl
def slamkit_plugins():
    return [PluginSpec("small_gicp", SmallGICPTracker, SmallGICPConfig)]
