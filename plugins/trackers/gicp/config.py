"""The G-ICP tracker's options (`tracker=gicp tracker.FIELD=VALUE`) and where its optimisation starts.

Two defaults differ from the reference code on purpose. `target_min_median` is off: map shapes
come from raw k-NN covariances whose median eigenvalue is far below the reference's 1e-3 m^2, so
that floor would make every target isotropic (docs/results.md, "Regularisation").
`target_geometry` is `entry`: the mapper reshapes and turns the millimetre-sized trackable
Gaussians for rendering, which moved the trajectory; aligning to the geometry they entered the
map with keeps it the tracking-only one (docs/tracking_under_mapping.md).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from slamkit.geometry.gaussians import Regularization
from slamkit.roles import PluginConfig, RunContext, method_setting, require, thread_count
from slamkit_plugins.trackers.gicp.kernels import Kernels

#: ms: no fallback of a frame starts after this much of its tracking (`frame_budget_ms`) when the
#: input does not wait (real time with realtime.drop_frames: a late frame costs the next ones): the issue's
#: 150 ms bound less the rest of a frame. Where the input waits, a fallback costs latency only and
#: a cut one costs accuracy on a slow CPU (docs/results.md).
REALTIME_BUDGET_MS = 100.0


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
    """Options of `tracker=gicp`, the paper's G-ICP tracking against the map's trackable Gaussians."""

    #: back-project every n-th pixel in x and y (null: the dataset's; reference 5 TUM, 10 Replica)
    pixel_stride: int | None = None
    #: neighbours (the point included) of each point's covariance
    knn: int = 10
    #: the covariances' regularisation: ellipse | plane | none (paper Table 5)
    regularization: Regularization = method_setting(Regularization.ellipse)
    #: the smallest eigenvalue of `plane` regularisation
    plane_eps: float = 1e-3
    #: m^2; with ellipse, a map covariance of smaller median eigenvalue becomes this x I (null: off; reference 1e-3)
    target_min_median: float | None = method_setting(None)
    #: metres (null: the dataset's; reference 0.03 TUM, 0.02 Replica)
    max_correspondence_distance: float | None = None
    #: Levenberg-Marquardt iterations, each finding the correspondences again
    max_iterations: int = 64
    #: converged when every entry of the last update's |dR - I| is below this
    rotation_tolerance: float = 2e-3
    #: metres; converged when every entry of the last update's |dt| is below this
    translation_tolerance: float = 5e-4
    #: map Gaussians at or below this opacity are not aligned to (0: all; null: the dataset's, 0.09 TUM, 0.05 Replica)
    min_target_opacity: float | None = method_setting(0.0)
    #: the target's means and shapes: entry (as they entered the map) | optimised (the mapper's; reference)
    target_geometry: TargetGeometry = method_setting(TargetGeometry.entry)
    #: where the optimisation starts: previous (pose) | constant_velocity (the last motion applied again)
    initial_guess: InitialGuess = method_setting(InitialGuess.constant_velocity)
    #: fewer valid trackable depth points: the frame is lost
    min_points: int = 100
    #: fewer matched points in an iteration: the frame is lost
    min_correspondences: int = 50
    #: a first alignment that fails or slides is run again from the previous pose (more matched points wins)
    fallback_to_previous: bool = method_setting(True)
    #: an alignment slides when it ends over this x max_correspondence_distance (RMS; <= 2x after drops) from its start
    fallback_slide: float = 2.0
    #: a first alignment that did not converge (matched, not slid) is tried again too (null: yes, in real time no)
    retry_unconverged: bool | None = method_setting(None)
    #: an alignment back within the tolerances of where it was 2-6 iterations before stops (null: in real time)
    stop_stalled: bool | None = None
    #: a first alignment that moves past the slide limit from its start stops there, slid (null: in real time)
    stop_slid: bool | None = None
    #: after dropped frames the prediction spans at most this many frame intervals of the last motion
    max_prediction_intervals: float = 4.0
    #: an alignment matching fewer of the trackable points is not trusted: the fallbacks run, else the frame is lost
    min_matched_fraction: float = 0.1
    #: nor, after dropped frames, one matching less than this x the last tracked frame's fraction (0: off)
    min_matched_ratio: float = 0.7
    #: metres: FPFH + RANSAC to the map at this voxel, then G-ICP, when nothing is trusted or after a long gap (0: off)
    relocalize_voxel: float = 0.05
    #: global registrations from up to this many RANSAC seeds: the next only while no alignment is trusted
    relocalize_restarts: int = 3
    #: after a long gap (sequential), trusted too: the map on the frame's depth in this fraction of cells (null: off)
    min_surface_agreement: float | None = 0.9
    #: ms from a frame's start: no fallback (nor its iterations) starts after it (null: 100 where frames drop; 0: none)
    frame_budget_ms: float | None = None
    #: a first alignment that fails or slides is also tried coarse to fine, from this x the distance (1: off)
    coarse_factor: float = method_setting(3.0)
    #: an update keeping the last one's direction goes on by at most this x itself (0: off; null: 2 in real time)
    extrapolation: float | None = None
    #: Levenberg-Marquardt's initial damping, relative to the normal matrix's largest diagonal entry
    lm_lambda: float = 1e-9
    #: damped steps tried per iteration before giving up on a cost decrease
    lm_max_tries: int = 10
    #: covariance and linearisation loops: auto | compiled (csrc/gicp_kernels.cpp) | numpy; same results
    kernels: Kernels = Kernels.auto
    #: threads of the compiled kernels, no effect on results (null: the run's, 1 in real time; 0: every CPU)
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
        require(self.max_prediction_intervals >= 1, "tracker.max_prediction_intervals", ">= 1",
                self.max_prediction_intervals)
        require(0 <= self.min_matched_fraction < 1, "tracker.min_matched_fraction", "in [0, 1)",
                self.min_matched_fraction)
        require(0 <= self.min_matched_ratio <= 1, "tracker.min_matched_ratio", "in [0, 1]", self.min_matched_ratio)
        require(self.relocalize_voxel >= 0, "tracker.relocalize_voxel", ">= 0 metres (0: off)",
                self.relocalize_voxel)
        require(self.relocalize_restarts >= 1, "tracker.relocalize_restarts", "an integer >= 1",
                self.relocalize_restarts)
        require(self.min_surface_agreement is None or 0 < self.min_surface_agreement <= 1,
                "tracker.min_surface_agreement", "null or in (0, 1]", self.min_surface_agreement)
        require(self.frame_budget_ms is None or self.frame_budget_ms >= 0, "tracker.frame_budget_ms",
                "null or >= 0 ms (0: no budget)", self.frame_budget_ms)
        require(self.fallback_slide > 0, "tracker.fallback_slide", "> 0", self.fallback_slide)
        require(self.coarse_factor >= 1, "tracker.coarse_factor", ">= 1 (1 disables)", self.coarse_factor)
        require(self.extrapolation is None or self.extrapolation >= 0, "tracker.extrapolation",
                "null or >= 0 (0: off)", self.extrapolation)
        require(self.lm_lambda >= 0, "tracker.lm_lambda", ">= 0", self.lm_lambda)
        require(self.lm_max_tries >= 1, "tracker.lm_max_tries", "an integer >= 1", self.lm_max_tries)
        require(self.num_threads is None or self.num_threads >= 0,
                "tracker.num_threads", "null or an integer >= 0 (0: all CPUs)", self.num_threads)

    def resolve(self, context: RunContext) -> GICPConfig:
        tuning = context.tuning
        return self.fill_nulls(pixel_stride=tuning.tracking_pixel_stride,
                               max_correspondence_distance=tuning.correspondence_distance,
                               min_target_opacity=tuning.target_min_opacity,
                               num_threads=context.tracking_threads,
                               # a live frame cannot wait for three more attempts of max_iterations
                               retry_unconverged=not context.realtime,
                               # a live camera does not wait: a frame's delay is bounded (issue 47)
                               stop_stalled=context.realtime,
                               # nor wait for the rest of a slide the fallbacks replace (docs/results.md, stop_slid)
                               stop_slid=context.realtime,
                               # nor for an alignment to slide a millimetre an iteration (docs/results.md)
                               extrapolation=2.0 if context.realtime else 0.0,
                               frame_budget_ms=REALTIME_BUDGET_MS if context.drops_frames else 0.0)
