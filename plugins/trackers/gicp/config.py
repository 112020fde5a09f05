"""The G-ICP tracker's options (`tracker=gicp tracker.FIELD=VALUE`) and where its optimisation starts."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from slamkit.geometry.gaussians import Regularization
from slamkit.roles import PluginConfig, RunContext, require, thread_count
from slamkit_plugins.trackers.gicp.kernels import Kernels


class TargetGeometry(enum.Enum):
    """Which geometry of the map's trackable Gaussians the target takes: entry (means and shapes
    as they entered the map) or optimised (the mapper's current ones, as the reference code)."""

    entry = "entry"
    optimised = "optimised"


class InitialGuess(enum.Enum):
    """Where the optimisation starts: the previous pose, or the previous pose moved by the
    last inter-frame motion (constant velocity)."""

    previous = "previous"
    constant_velocity = "constant_velocity"


@dataclass
class GICPConfig(PluginConfig):
    """G-ICP tracker options. pixel_stride and max_correspondence_distance left null take the
    dataset's tuning (`DatasetTuning`: (tracking_pixel_stride, correspondence_distance).

    pixel_stride: back-project every n-th pixel in x and y (reference: 5 TUM, 10 Replica).
    knn: neighbours (the point included) of each point's covariance.
    regularization: ellipse | plane | none (paper Table 5).
    plane_eps: the smallest eigenvalue of `plane` regularisation.
    target_min_median: m^2; with ellipse, a map covariance whose median eigenvalue is below
      this becomes target_min_median * I (the reference code uses 1e-3). Off by default: map
      shapes come from raw k-NN covariances scale-aligned by 1/max(c z^1.5, 1) (c = 2 in the
      reference code, 1 here), whose median eigenvalue is ~1e-6..1e-5 m^2 (with c = 2; up to 4x
      that with c = 1), so the reference's 1e-3 makes every target isotropic (TUM fr1/rpy, c =
      2: 6.57 cm ATE RMSE against 4.91 cm off; docs/results.md).
    max_correspondence_distance: metres (reference: 0.03 TUM, 0.02 Replica).
    max_iterations: Levenberg-Marquardt iterations (each re-finds correspondences).
    rotation_tolerance, translation_tolerance: converged when every |dR - I| entry and every
      |dt| entry (metres) of the last update is below these.
    min_target_opacity: map Gaussians at or below this opacity are not aligned to (0: every
      trackable Gaussian pruning left; null: the dataset's `DatasetTuning.target_min_opacity`,
      the reference code's 0.09 TUM / 0.05 Replica with the optimised geometry, new Gaussians
      entering at 0.1).
    target_geometry: entry | optimised: the target takes the trackable Gaussians' means and
      shapes as they entered the map (the default), or as the mapper has optimised them (the
      reference code). The mapper reshapes and turns these 1-3 mm Gaussians for rendering (TUM
      fr1/rpy: normals turned by 7-14 degrees median), which cost 28% mean ATE over four start
      frames; with `entry` the trajectory is the tracking-only run's, whatever mapping does
      (docs/tracking_under_mapping.md).
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
    min_target_opacity: float | None = 0.0
    target_geometry: TargetGeometry = TargetGeometry.entry
    initial_guess: InitialGuess = InitialGuess.constant_velocity
    min_points: int = 100
    min_correspondences: int = 50
    fallback_to_previous: bool = True
    fallback_slide: float = 2.0
    coarse_factor: float = 3.0
    lm_lambda: float = 1e-9
    lm_max_tries: int = 10
    kernels: Kernels = Kernels.auto
    num_threads: int | None = thread_count(None)

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
        require(self.min_target_opacity is None or 0 <= self.min_target_opacity < 1, "tracker.min_target_opacity",
                "null or in [0, 1)", self.min_target_opacity)
        require(self.min_points >= 1, "tracker.min_points", "an integer >= 1", self.min_points)
        require(self.min_correspondences >= 6,
                "tracker.min_correspondences", "an integer >= 6", self.min_correspondences)
        require(self.fallback_slide > 0, "tracker.fallback_slide", "> 0", self.fallback_slide)
        require(self.coarse_factor >= 1, "tracker.coarse_factor", ">= 1 (1 disables)", self.coarse_factor)
        require(self.lm_lambda >= 0, "tracker.lm_lambda", ">= 0", self.lm_lambda)
        require(self.lm_max_tries >= 1, "tracker.lm_max_tries", "an integer >= 1", self.lm_max_tries)
        require(self.num_threads is None or self.num_threads >= 0,
                "tracker.num_threads", "null or an integer >= 0 (0: all CPUs)", self.num_threads)

    def resolve(self, context: RunContext) -> GICPConfig:
        tuning = context.tuning
        return self.fill_nulls(pixel_stride=tuning.tracking_pixel_stride,
                               max_correspondence_distance=tuning.correspondence_distance,
                               min_target_opacity=tuning.target_min_opacity,
                               num_threads=context.tracking_threads)
