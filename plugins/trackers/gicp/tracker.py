"""G-ICP tracking against the shared Gaussian map (paper Sec. 3.1; Segal et al. 2009).

Each frame's depth is back-projected on a fixed pixel grid (every `pixel_stride`-th pixel,
no voxel filter); every point gets a covariance from its `knn` nearest neighbours (the source
Gaussians), regularised (`ellipse` by default). The target is the map's trackable Gaussians
with opacity above `min_target_opacity`, their covariances R diag(s^2) R^T regularised the
same way (the reference code's rule that a map covariance with a median eigenvalue below 1e-3
becomes 1e-3 I is `target_min_median`, off by default: see GICPConfig). The pose minimises

    sum_i d_i^T (C_t,i + R C_s,i R^T)^-1 d_i,   d_i = mu_t,i - (R p_i + t)

by Levenberg-Marquardt on SE(3) (right perturbation T <- T exp(xi)), re-finding each source
point's nearest target mean within `max_correspondence_distance` at every iteration. The
target's KD-tree is built once per tracking keyframe, in `update_target`, never per frame.
Only trackable points (depth <= the frame's depth_trunc) are aligned; all get covariances.

The optimisation starts from a constant-velocity prediction (measured better than the
reference code's previous pose on TUM fr1/rpy: 4.5 vs 6.2 cm mean ATE over seven start
frames; equal on Replica). If it slides away or fails from there, it is run again from the
previous pose (a sudden stop) and coarse to fine from the prediction (a motion the prediction
missed by more than the correspondence distance), and the result matching more points is kept.

The loops over points (k-NN covariances, nearest-neighbour search, normal equations) run in
compiled kernels or their numpy reference (`.kernels`); both give the same trajectory.

The frame's Gaussians (world means at the final pose, regularised covariances rotated to the
world, colours, depths, squared distance to the nearest target mean from the last
correspondence search) are returned for the keyframe policy and for map growth.
"""

from __future__ import annotations

import enum
import time
from dataclasses import dataclass

import numpy as np

from slamkit.geometry.gaussians import Regularization, regularize, rotate_covariances
from slamkit.map.gaussian_map import GaussianMap
from slamkit.geometry.transforms import backproject, invert_pose, se3_exp
from slamkit.roles import PluginConfig, SensorProfile, Tracker, require
from slamkit.types import Frame, FrameGaussians, TrackingResult
from slamkit_plugins.trackers.gicp.kernels import Kernels, create_kernels


#: Stats summed over all attempts at a frame.
_EFFORT = ("nn_search_s", "solve_s", "iterations")


class InitialGuess(enum.Enum):
    """Where the optimisation starts: the previous pose, or the previous pose moved by the
    last inter-frame motion (constant velocity)."""

    previous = "previous"
    constant_velocity = "constant_velocity"


@dataclass
class GICPConfig(PluginConfig):
    """G-ICP tracker options. pixel_stride, max_correspondence_distance and min_target_opacity
    left null take the dataset's `SensorProfile` values (tracking_pixel_stride,
    correspondence_distance, min_target_opacity).

    pixel_stride: back-project every n-th pixel in x and y (reference: 5 TUM, 10 Replica).
    knn: neighbours (the point included) of each point's covariance.
    regularization: ellipse | plane | none (paper Table 5).
    plane_eps: the smallest eigenvalue of `plane` regularisation.
    target_min_median: m^2; with ellipse, a map covariance whose median eigenvalue is below
      this becomes target_min_median * I (the reference code uses 1e-3). Off by default: map
      shapes come from raw k-NN covariances scale-aligned by 1/max(2 z^1.5, 1), whose median
      eigenvalue is ~1e-6..1e-5 m^2, so the reference's 1e-3 makes every target isotropic
      (TUM fr1/rpy: 6.57 cm ATE RMSE against 4.91 cm off; docs/results.md).
    max_correspondence_distance: metres (reference: 0.03 TUM, 0.02 Replica).
    max_iterations: Levenberg-Marquardt iterations (each re-finds correspondences).
    rotation_tolerance, translation_tolerance: converged when every |dR - I| entry and every
      |dt| entry (metres) of the last update is below these.
    min_target_opacity: map Gaussians at or below this opacity are not aligned to.
    initial_guess: previous | constant_velocity.
    fallback_to_previous: when G-ICP from a constant-velocity start does not converge, loses
      the frame, or ends farther than fallback_slide * max_correspondence_distance (RMS
      displacement of the points) from its start (it slid, e.g. after a sudden stop), run it
      again from the previous pose and keep the result with more correspondences.
    fallback_slide: that distance, in units of max_correspondence_distance.
    coarse_factor: then also try coarse to fine: align from the prediction with this times the
      correspondence distance, then with the distance itself (1 disables).
    min_points: fewer valid trackable depth points -> the frame is lost.
    min_correspondences: fewer matched points in an iteration -> the frame is lost.
    lm_lambda: initial damping relative to the largest diagonal entry of the normal matrix.
    lm_max_tries: damped steps tried per iteration before giving up on a cost decrease.
    kernels: auto | compiled | numpy: the covariance and linearisation loops compiled from
      csrc/gicp_kernels.cpp (built on first use; auto falls back to numpy without a compiler)
      or the numpy reference. Same results either way.
    num_threads: threads of the compiled kernels (results do not depend on it). Null: the run's
      choice (`Tracker.use_threads`), one in real-time mode (the mapper has the other CPUs:
      waiting for a thread it has descheduled costs more than the thread saves) and every CPU
      otherwise; 0: every CPU.
    """

    pixel_stride: int | None = None
    knn: int = 10
    regularization: Regularization = Regularization.ellipse
    plane_eps: float = 1e-3
    target_min_median: float | None = None
    max_correspondence_distance: float | None = None
    max_iterations: int = 64
    rotation_tolerance: float = 2e-3
    translation_tolerance: float = 5e-4
    min_target_opacity: float | None = None
    initial_guess: InitialGuess = InitialGuess.constant_velocity
    min_points: int = 100
    min_correspondences: int = 50
    fallback_to_previous: bool = True
    fallback_slide: float = 2.0
    coarse_factor: float = 3.0
    lm_lambda: float = 1e-9
    lm_max_tries: int = 10
    kernels: Kernels = Kernels.auto
    num_threads: int | None = None

    def validate(self) -> None:
        require(self.pixel_stride is None or self.pixel_stride >= 1,
                "tracker.pixel_stride", "null or an integer >= 1", self.pixel_stride)
        require(self.knn >= 3, "tracker.knn", "an integer >= 3", self.knn)
        require(0 < self.plane_eps <= 1, "tracker.plane_eps", "in (0, 1]", self.plane_eps)
        require(self.target_min_median is None or self.target_min_median >= 0,
                "tracker.target_min_median", "null or >= 0 m^2", self.target_min_median)
        require(
            self.max_correspondence_distance is None or self.max_correspondence_distance > 0,
            "tracker.max_correspondence_distance", "null or > 0 metres", self.max_correspondence_distance,
        )
        require(self.max_iterations >= 1, "tracker.max_iterations", "an integer >= 1", self.max_iterations)
        require(self.rotation_tolerance > 0, "tracker.rotation_tolerance", "> 0", self.rotation_tolerance)
        require(self.translation_tolerance > 0,
                "tracker.translation_tolerance", "> 0 metres", self.translation_tolerance)
        require(
            self.min_target_opacity is None or 0 <= self.min_target_opacity < 1,
            "tracker.min_target_opacity", "null or in [0, 1)", self.min_target_opacity,
        )
        require(self.min_points >= 1, "tracker.min_points", "an integer >= 1", self.min_points)
        require(self.min_correspondences >= 6,
                "tracker.min_correspondences", "an integer >= 6", self.min_correspondences)
        require(self.fallback_slide > 0, "tracker.fallback_slide", "> 0", self.fallback_slide)
        require(self.coarse_factor >= 1, "tracker.coarse_factor", ">= 1 (1 disables)", self.coarse_factor)
        require(self.lm_lambda >= 0, "tracker.lm_lambda", ">= 0", self.lm_lambda)
        require(self.lm_max_tries >= 1, "tracker.lm_max_tries", "an integer >= 1", self.lm_max_tries)
        require(self.num_threads is None or self.num_threads >= 0,
                "tracker.num_threads", "null or an integer >= 0 (0: all CPUs)", self.num_threads)

    def with_sensor(self, sensor: SensorProfile) -> GICPConfig:
        return self.fill_nulls(pixel_stride=sensor.tracking_pixel_stride,
                               max_correspondence_distance=sensor.correspondence_distance,
                               min_target_opacity=sensor.min_target_opacity)


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """The pose with its rotation block projected onto SO(3) (nearest rotation, by SVD), so
    rounding cannot accumulate through pose products."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    out = T.copy()
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


class _Target:
    """The aligned-to map Gaussians: means (float32 for the search and float64 for residuals),
    regularised covariances (float64) and the nearest-neighbour index over the means."""

    def __init__(self, means: np.ndarray, covariances: np.ndarray, version: int, kernels):
        self.means32 = np.ascontiguousarray(means, dtype=np.float32)
        # Means and covariances side by side: one gather per iteration.
        self.packed = np.concatenate([self.means32.astype(np.float64), covariances.reshape(-1, 9)], axis=1)
        self.version = version
        self.index = kernels.nearest_index(self.means32)

    @property
    def means(self) -> np.ndarray:
        return self.packed[:, :3]

    @property
    def covariances(self) -> np.ndarray:
        return self.packed[:, 3:].reshape(-1, 3, 3)

    def __len__(self) -> int:
        return len(self.means)


class GICPTracker(Tracker):
    """Frame-to-map G-ICP on the shared Gaussian map (see the module docstring).

    `tree_builds` counts target KD-tree builds (one per `update_target` with a non-empty
    target)."""

    def __init__(self, cfg: GICPConfig):
        self.cfg = cfg
        for name in ("pixel_stride", "max_correspondence_distance", "min_target_opacity"):
            require(getattr(cfg, name) is not None, f"tracker.{name}", "a value (GICPConfig.with_sensor fills it from the dataset)", None)
        self.pixel_stride = int(cfg.pixel_stride)
        self.max_corr = float(cfg.max_correspondence_distance)
        self.min_opacity = float(cfg.min_target_opacity)
        self.regularization = Regularization(cfg.regularization)
        self.initial_guess = InitialGuess(cfg.initial_guess)
        self.kernels = create_kernels(cfg.kernels, cfg.num_threads or 0)
        self.target: _Target | None = None
        self.tree_builds = 0
        self.poses: list[np.ndarray] = []
        self.first_pose = np.eye(4)

    # ---------------------------------------------------------------- role API
    def initialize(self, first_pose: np.ndarray) -> None:
        self.first_pose = orthonormalize(np.asarray(first_pose, dtype=np.float64))
        self.poses = []

    def use_threads(self, threads: int) -> None:
        if self.cfg.num_threads is None:
            self.kernels.num_threads = threads

    def update_target(self, gaussian_map: GaussianMap) -> None:
        """Take the map's trackable Gaussians as the new target; regularise their covariances
        and build the KD-tree (the only place it is built)."""
        snap = gaussian_map.tracking_target(self.min_opacity)
        if len(snap.means) == 0:
            self.target = None
            return
        cov = self._regularize(snap.covariances, target=True)
        self.target = _Target(snap.means, cov, snap.version, self.kernels)
        self.tree_builds += 1

    def predict(self) -> np.ndarray:
        """The pose the optimisation starts from (camera-to-world)."""
        if not self.poses:
            return self.first_pose.copy()
        if self.initial_guess is InitialGuess.constant_velocity and len(self.poses) >= 2:
            prev, last = self.poses[-2], self.poses[-1]
            return orthonormalize(last @ (invert_pose(prev) @ last))
        return self.poses[-1].copy()

    @staticmethod
    def _moved(src: np.ndarray, start: np.ndarray, end: np.ndarray) -> float:
        """RMS displacement in metres of the source points between two poses."""
        D = invert_pose(start) @ end
        return float(np.sqrt(np.mean(np.sum((src @ (D[:3, :3] - np.eye(3)).T + D[:3, 3]) ** 2, axis=1))))

    def _fallback_start(self, predicted: np.ndarray) -> np.ndarray | None:
        """The previous pose, when the motion model moved the start away from it and
        `fallback_to_previous` is on; else None."""
        if not (self.cfg.fallback_to_previous and self.poses):
            return None
        last = self.poses[-1]
        return None if np.array_equal(last, predicted) else last.copy()

    def track(self, frame: Frame, gaussian_map: GaussianMap) -> TrackingResult:
        predicted = self.predict()
        result = self._track(frame, predicted)
        self.poses = self.poses[-1:] + [result.pose]  # the motion model needs the last two
        return result

    # ---------------------------------------------------------------- internals
    def _regularize(self, cov: np.ndarray, target: bool) -> np.ndarray:
        min_median = self.cfg.target_min_median if target else None
        return regularize(cov, self.regularization, self.cfg.plane_eps, min_median=min_median)

    def _track(self, frame: Frame, predicted: np.ndarray) -> TrackingResult:
        cfg = self.cfg
        stats = self._new_stats()
        t0 = time.perf_counter()
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
            pose, ok, sq_track = self._solve(src, src_cov, predicted, stats)
            if not ok:
                return TrackingResult(pose=predicted, lost=True, stats=stats)

        sq_dist = np.full(len(points), np.inf)
        sq_dist[trackable] = sq_track
        R, t = pose[:3, :3], pose[:3, 3]
        rgb = np.asarray(frame.rgb).reshape(-1, 3)[pix]
        if np.issubdtype(rgb.dtype, np.integer):
            colors = rgb.astype(np.float32) / 255.0
        else:
            colors = np.clip(rgb, 0.0, 1.0).astype(np.float32)
        gaussians = FrameGaussians(
            means=(points.astype(np.float64) @ R.T + t).astype(np.float32),
            covariances=rotate_covariances(R, cov_cam),
            shape_covariances=rotate_covariances(R, raw_cam),
            colors=colors,
            depths=z.copy(),
            trackable=trackable,
            sq_dist_to_map=sq_dist,
        )
        stats["matched_fraction"] = float(np.isfinite(sq_track).mean()) if n_track else 0.0
        return TrackingResult(pose=pose, lost=False, gaussians=gaussians, stats=stats)

    @staticmethod
    def _new_stats() -> dict:
        return {"covariance_s": 0.0, "nn_search_s": 0.0, "solve_s": 0.0, "iterations": 0}

    def _solve(self, src: np.ndarray, src_cov: np.ndarray, predicted: np.ndarray, stats: dict):
        """G-ICP from the prediction. When that does not converge, loses the frame or slides
        (ends more than fallback_slide * max_correspondence_distance RMS from its start), it is
        tried again from the previous pose and, with coarse_factor > 1, from the prediction
        first aligned with a coarse_factor times larger correspondence distance (a motion the
        prediction missed by more than the fine distance); the result matching more points wins."""
        pose, ok, sq = self._align(src, src_cov, predicted, stats)
        slide_limit = self.cfg.fallback_slide * self.max_corr
        if ok and stats["converged"] and self._moved(src, predicted, pose) <= slide_limit:
            return pose, ok, sq
        best = (pose, ok, sq, stats.get("num_correspondences", 0) if ok else -1)
        for name, start, coarse in self._fallback_starts(predicted):
            retry = self._new_stats()
            if coarse:
                start, ok_coarse, _ = self._align(src, src_cov, start, retry, self.max_corr * self.cfg.coarse_factor)
                if not ok_coarse:
                    self._add_effort(stats, retry)
                    continue
            pose2, ok2, sq2 = self._align(src, src_cov, start, retry)
            if coarse and ok2 and self._moved(src, start, pose2) > slide_limit:
                # the fine stage slid away from the coarse alignment: keep the coarse pose
                pose2, sq2 = start, self._match(src, start)
                retry["num_correspondences"] = int(np.isfinite(sq2).sum())
            self._add_effort(stats, retry)
            stats.setdefault("retried", []).append(name)
            if ok2 and retry["num_correspondences"] > best[3]:
                stats.pop("lost_reason", None)
                stats.update({k: v for k, v in retry.items() if k not in _EFFORT and k != "covariance_s"})
                stats["fallback"] = name
                best = (pose2, ok2, sq2, retry["num_correspondences"])
        return best[:3]

    def _fallback_starts(self, predicted: np.ndarray):
        """(name, start pose, coarse first?) of the attempts after the first one failed."""
        previous = self._fallback_start(predicted)
        if previous is not None:
            yield "previous pose", previous, False
        if self.cfg.coarse_factor > 1:
            yield "coarse to fine", predicted, True

    def _match(self, src: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Squared distance (m^2) of each source point at `pose` to its nearest target mean
        within max_correspondence_distance (inf where none)."""
        query = (src @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
        return self.target.index.nearest(query, self.max_corr)[0].astype(np.float64)

    @staticmethod
    def _add_effort(stats: dict, retry: dict) -> None:
        for key in _EFFORT:
            stats[key] += retry[key]

    def _align(self, src: np.ndarray, src_cov: np.ndarray, T0: np.ndarray, stats: dict,
               max_corr: float | None = None):
        """Levenberg-Marquardt G-ICP from T0. Returns (pose, ok, squared NN distances of the
        last correspondence search (inf where none)).

        Residuals are taken in the body frame: r_i = R^T (mu_i - R p_i - t) with weight
        W_i = (R^T C_t,i R + C_s,i)^-1 = G_i^T G_i (G_i: inverse Cholesky factor; the
        pseudo-inverse where singular), and T <- T exp(xi), xi = (omega, v), for which
        dr_i/dxi = [[p_i]x, -I]."""
        cfg, target = self.cfg, self.target
        n_target = len(target)
        packed_src = np.concatenate([src, src_cov.reshape(-1, 9)], axis=1)
        T = T0.copy()
        lam = None
        nu = 2.0
        sq = np.full(len(src), np.inf)
        idx = None  # the last matches: each search starts from them
        converged = False
        for it in range(cfg.max_iterations):
            stats["iterations"] = it + 1
            R, t = T[:3, :3], T[:3, 3]
            query = (src @ R.T + t).astype(np.float32)
            ts = time.perf_counter()
            d2, idx = target.index.nearest(query, max_corr or self.max_corr, hint=idx)
            te = time.perf_counter()
            stats["nn_search_s"] += te - ts
            sq = d2.astype(np.float64)
            m = int(np.count_nonzero(idx < n_target))
            stats["num_correspondences"] = m
            if m < cfg.min_correspondences:
                stats["lost_reason"] = f"too few correspondences ({m} < {cfg.min_correspondences})"
                stats["solve_s"] += time.perf_counter() - te
                return T0, False, sq
            lin = self.kernels.linearize(packed_src, target.packed, idx, T)
            H, g, cost0 = lin.H, lin.g, lin.cost
            if lam is None:
                lam = cfg.lm_lambda * float(np.max(np.diag(H)))
            accepted = False
            for _ in range(cfg.lm_max_tries):
                try:
                    xi = np.linalg.solve(H + lam * np.eye(6), -g)
                except np.linalg.LinAlgError:
                    xi = np.linalg.lstsq(H + lam * np.eye(6), -g, rcond=None)[0]
                delta = se3_exp(xi)
                Tn = T @ delta
                cost = lin.cost_at(Tn)  # same correspondences and weights
                small = self._small(delta)
                rho_den = float(xi @ (lam * xi - g))
                rho = (cost0 - cost) / rho_den if rho_den > 0 else -1.0
                if cost <= cost0 or rho > 0:
                    T = Tn
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3) if rho > 0 else 1.0
                    nu = 2.0
                    accepted = True
                    converged = small
                    break
                if small:
                    converged = True
                    break
                lam *= nu
                nu *= 2.0
            stats["solve_s"] += time.perf_counter() - te
            stats["singular_covariances"] = lin.singular
            if converged or not accepted:
                break
        stats["converged"] = bool(converged)
        if not np.isfinite(T).all():
            stats["lost_reason"] = "non-finite pose"
            return T0, False, sq
        return orthonormalize(T), True, sq

    def _small(self, delta: np.ndarray) -> bool:
        return bool(
            np.abs(delta[:3, :3] - np.eye(3)).max() < self.cfg.rotation_tolerance
            and np.abs(delta[:3, 3]).max() < self.cfg.translation_tolerance
        )
