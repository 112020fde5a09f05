"""G-ICP tracking against the shared Gaussian map (paper Sec. 3.1; Segal et al. 2009).

Source: the frame's depth back-projected every `pixel_stride`-th pixel, each point with a
covariance from its `knn` nearest neighbours, regularised; the trackable ones (depth <=
depth_trunc) are aligned. Target: the map's trackable Gaussians with the geometry they entered
the map with (`target_geometry`), their covariances R diag(s^2) R^T regularised the same way,
indexed once per tracking keyframe (`update_target`). The camera-to-world pose minimises

    sum_i d_i^T (C_t,i + R C_s,i R^T)^-1 d_i,   d_i = mu_t,i - (R p_i + t)

by Levenberg-Marquardt on SE(3) (T <- T exp(xi)), matching each point to its nearest target mean
within `max_correspondence_distance` at every iteration, from a constant-velocity prediction
(docs/results.md, "Robustness of a single run") with the fallbacks of `.fallbacks`. The frame's
Gaussians (world frame) are handed over to the keyframe policy and the map's growth.
"""

from __future__ import annotations

import time

import numpy as np

from slamkit.geometry.gaussians import Regularization
from slamkit.geometry.surface import surface_cells
from slamkit.geometry.transforms import backproject, invert_pose, motion_power
from slamkit.map.gaussian_map import GaussianMap
from slamkit.map.growth import gaussians_at_pose
from slamkit.roles import RunContext, Tracker, require
from slamkit.types import Frame, FrameGaussians, TrackingResult
from slamkit_plugins.trackers.gicp.alignment import Aligner, matched_fraction, new_stats, orthonormalize
from slamkit_plugins.trackers.gicp.config import GICPConfig, InitialGuess, TargetGeometry
from slamkit_plugins.trackers.gicp.fallbacks import FallbackPolicy
from slamkit_plugins.trackers.gicp.kernels import create_kernels
from slamkit_plugins.trackers.gicp.target import Target

#: Image cells seeing the map, at least, for its surface agreement to judge a pose: an agreement
#: over a few cells (a corner of the map in view) says little.
MIN_SURFACE_CELLS = 20


class GICPTracker(Tracker):
    """Frame-to-map G-ICP on the shared Gaussian map (see the module docstring).

    `tree_builds` counts target nearest-neighbour index builds (one per `update_target` with a
    non-empty target)."""

    def __init__(self, cfg: GICPConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        for name in ("pixel_stride", "max_correspondence_distance", "min_target_opacity"):
            require(getattr(cfg, name) is not None, f"tracker.{name}",
                    "a value (GICPConfig.resolve fills it from the dataset)", None)
        self.pixel_stride = int(cfg.pixel_stride)
        self.max_corr = float(cfg.max_correspondence_distance)
        self.min_opacity = float(cfg.min_target_opacity)
        self.regularization = Regularization(cfg.regularization)
        self.initial_guess = InitialGuess(cfg.initial_guess)
        self.kernels = create_kernels(cfg.kernels, cfg.num_threads or 0)
        self.aligner = Aligner(cfg, self.kernels, self.max_corr)
        self.fallbacks = FallbackPolicy(cfg, self.aligner)
        self.target: Target | None = None
        self.tree_builds = 0
        self.poses: list[np.ndarray] = []
        self.frame_indices: list[int] = []  # the dataset indices of `poses`' frames
        self.first_pose = np.eye(4)
        self.last_matched: float | None = None  # the last tracked frame's matched fraction

    # ---------------------------------------------------------------- role API
    def initialize(self, first_pose: np.ndarray) -> None:
        self.first_pose = orthonormalize(np.asarray(first_pose, dtype=np.float64))
        self.poses, self.frame_indices = [], []
        self.last_matched = None

    def move_world(self, motion: np.ndarray) -> None:
        """The motion model's poses move with the world (the velocity between them is kept)."""
        motion = np.asarray(motion, dtype=np.float64)
        self.poses = [orthonormalize(motion @ p) for p in self.poses]
        self.first_pose = orthonormalize(motion @ self.first_pose)

    def update_target(self, gaussian_map: GaussianMap) -> None:
        """Take the map's trackable Gaussians as the new target; regularise their covariances
        and build their nearest-neighbour index (the only place it is built)."""
        snap = gaussian_map.tracking_target(self.min_opacity, TargetGeometry(self.cfg.target_geometry).value)
        if len(snap.means) == 0:
            self.target = None
            return
        cov = self._regularize(snap.covariances, target=True)
        self.target = Target(snap.means, cov, snap.version, self.kernels, self.max_corr)
        self.tree_builds += 1

    def state_dict(self) -> dict:
        """The motion model's last two poses, the first pose, and the target (means, regularised
        covariances and the map version they were taken at)."""
        state = {"first_pose": self.first_pose, "poses": np.array(self.poses).reshape(-1, 4, 4),
                 "frame_indices": list(self.frame_indices), "tree_builds": self.tree_builds,
                 "last_matched": self.last_matched}
        if self.target is not None:
            state["target"] = {"means": self.target.means32, "covariances": self.target.covariances.copy(),
                               "version": self.target.version}
        return state

    def load_state_dict(self, state: dict) -> None:
        self.first_pose = np.asarray(state["first_pose"], dtype=np.float64)
        self.poses = list(np.asarray(state["poses"], dtype=np.float64).reshape(-1, 4, 4))
        self.frame_indices = [int(i) for i in state.get("frame_indices", [])]  # older checkpoints: no gap assumed
        self.tree_builds = int(state.get("tree_builds", 0))
        self.last_matched = state.get("last_matched")  # older checkpoints: none (no ratio for the next frame)
        target = state.get("target")
        self.target = None if target is None else Target(np.asarray(target["means"]), np.asarray(
            target["covariances"], dtype=np.float64), int(target["version"]), self.kernels, self.max_corr)

    def predict(self, frame_index: int | None = None) -> np.ndarray:
        """The pose the optimisation starts from (camera-to-world) for the frame of dataset index
        `frame_index`. With constant velocity, the last motion is taken once per frame interval
        since the last frame: after frames were dropped (`realtime.drop_frames`) the prediction goes as
        far as the camera went (without it, the alignment starts a few motions short and needs
        more iterations and fallbacks, which makes the next frame late in turn)."""
        return self._predicted(self._intervals(frame_index))

    def _predicted(self, intervals: float) -> np.ndarray:
        """`predict` for a frame `intervals` frame intervals after the last tracked one."""
        if not self.poses:
            return self.first_pose.copy()
        if self.initial_guess is InitialGuess.constant_velocity and len(self.poses) >= 2:
            prev, last = self.poses[-2], self.poses[-1]
            motion = invert_pose(prev) @ last
            return orthonormalize(last @ (motion if intervals == 1.0 else motion_power(motion, intervals)))
        return self.poses[-1].copy()

    def _gap(self, frame_index: int | None) -> float:
        """How many times the last motion (between the last two tracked frames) the camera made
        by `frame_index`: the ratio of the frame gaps (1 without indices or a gap)."""
        if frame_index is None or len(self.frame_indices) != len(self.poses) or len(self.poses) < 2:
            return 1.0
        before, last = self.frame_indices[-2], self.frame_indices[-1]
        if last <= before or frame_index <= last:
            return 1.0
        return (frame_index - last) / (last - before)

    def _intervals(self, frame_index: int | None) -> float:
        """`_gap`, at most `max_prediction_intervals`: the motions the prediction spans."""
        # capped: over a long gap the camera does not keep its velocity, and the prediction went
        # far enough off for an alignment to converge to a wrong pose (7-Scenes 157 -> 175: 96 cm)
        return min(self._gap(frame_index), self.cfg.max_prediction_intervals)

    def track(self, frame: Frame) -> TrackingResult:
        intervals = self._intervals(frame.index)
        result = self._track(frame, self._predicted(intervals), intervals,
                             beyond_prediction=self._gap(frame.index) > self.cfg.max_prediction_intervals)
        self.poses = self.poses[-1:] + [result.pose]  # the motion model needs the last two
        self.frame_indices = self.frame_indices[-1:] + [frame.index]
        return result

    # ---------------------------------------------------------------- internals
    def _regularize(self, cov: np.ndarray, target: bool) -> np.ndarray:
        min_median = self.cfg.target_min_median if target else None
        return self.kernels.regularize(cov, self.regularization, self.cfg.plane_eps, min_median=min_median)

    def _track(self, frame: Frame, predicted: np.ndarray, intervals: float = 1.0,
               beyond_prediction: bool = False) -> TrackingResult:
        """`intervals`: frame intervals the prediction spans (> 1 after dropped frames);
        `beyond_prediction`: the gap since the last tracked frame is longer (`FallbackPolicy.solve`)."""
        cfg = self.cfg
        stats = new_stats()
        t0 = time.perf_counter()
        budget = self.cfg.frame_budget_ms
        deadline = t0 + budget / 1e3 if budget else None
        depth = np.asarray(frame.depth)
        if not np.isfinite(depth).all():
            depth = np.where(np.isfinite(depth), depth, 0.0)
        points, pix = backproject(depth, frame.camera, self.pixel_stride)
        z = points[:, 2]
        trackable = z <= frame.depth_trunc
        n_track = int(trackable.sum())
        stats["num_points"] = len(points)
        stats["num_trackable"] = n_track
        if n_track < cfg.min_points or len(points) < cfg.knn:
            stats["lost_reason"] = f"too few valid depth points ({n_track} < {cfg.min_points})"
            return TrackingResult(pose=predicted, lost=True, stats=stats)

        raw_cam = self.kernels.frame_covariances(points, pix, frame.camera, self.pixel_stride, cfg.knn)
        cov_cam = self._regularize(raw_cam, target=False)
        stats["covariance_s"] = time.perf_counter() - t0

        src = points[trackable].astype(np.float64)
        src_cov = cov_cam[trackable]
        sq_track = np.full(n_track, np.inf)
        pose = predicted
        if self.target is None or len(self.target) == 0:
            stats["note"] = "no target yet"
        else:
            previous = self.poses[-1] if self.poses else None
            target = self.target

            def map_agreement(at: np.ndarray) -> float | None:
                """The map's surface agreement with the frame seen from `at` (camera-to-world):
                judged per attempt after a long gap (`FallbackPolicy.solve`)."""
                cells = surface_cells(target.means, depth, frame.camera, at)
                return cells.agreement if len(cells.on) >= MIN_SURFACE_CELLS else None

            pose, ok, sq_track = self.fallbacks.solve(target, src, src_cov, predicted, previous, stats, intervals,
                                                      deadline, self.last_matched, beyond_prediction, map_agreement)
            if not ok:
                return TrackingResult(pose=predicted, lost=True, stats=stats)

        gaussians = self._frame_gaussians(frame, points, pix, trackable, pose, cov_cam, raw_cam, sq_track)
        stats["matched_fraction"] = matched_fraction(sq_track)
        if self.target is not None and len(self.target):
            self.last_matched = stats["matched_fraction"]
        return TrackingResult(pose=pose, lost=False, gaussians=gaussians, stats=stats)

    @staticmethod
    def _frame_gaussians(frame: Frame, points: np.ndarray, pix: np.ndarray, trackable: np.ndarray, pose: np.ndarray,
                         cov_cam: np.ndarray, raw_cam: np.ndarray, sq_track: np.ndarray) -> FrameGaussians:
        """The frame's Gaussians at `pose`, handed over to the map's growth (which would otherwise
        make them again: `slamkit.map.growth.frame_gaussians`), with the trackable points'
        squared distance (m^2) to their nearest target mean (inf elsewhere)."""
        sq_dist = np.full(len(points), np.inf)
        sq_dist[trackable] = sq_track
        return gaussians_at_pose(frame, pose, points, pix, trackable, cov_cam, raw_cam, sq_dist)
