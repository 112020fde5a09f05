"""The pose-graph loop closure's options (`loop_closure=pose_graph loop_closure.FIELD=VALUE`)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from slamkit.roles import PluginConfig, RunContext, method_setting, require


class Backend(enum.Enum):
    """The pose-graph optimiser: gtsam's Levenberg-Marquardt with robust loop edges, or
    open3d's global optimisation (Levenberg-Marquardt with a line process on loop edges)."""

    gtsam = "gtsam"
    open3d = "open3d"


class WeakDirection(enum.Enum):
    """What becomes of a loop constrained less than `min_constraint` along its weakest direction."""

    reject = "reject"  # refused (loops.csv says by how much)
    free = "free"  # kept, that direction marginalised out of its information (the graph places the pose along it)


@dataclass
class PoseGraphConfig(PluginConfig):
    """Options of `loop_closure=pose_graph`: detection, verification and optimisation."""

    #: metres: the keyframes' points are downsampled to one per voxel for registration (FPFH radius 5 voxels).
    voxel: float = 0.025
    #: a keyframe's candidates are among the keyframes before its last `exclude_recent` ones.
    exclude_recent: int = 10
    #: metres of camera path between a candidate and the keyframe, at least (a shorter gap is odometry's job).
    min_path_m: float = 1.0
    #: metres between the places two keyframes look at (centre + median depth along the axis), with no path between
    search_radius_m: float = 0.3
    #: metres added to search_radius_m per metre of camera path between the two keyframes (drift grows with the path).
    radius_per_path: float = 0.05
    #: degrees between the two cameras' optical axes, at most.
    max_view_angle_deg: float = 45.0
    #: cosine similarity of the two keyframes' appearance descriptors (zero-mean 32x24 grey images), at least.
    min_appearance: float = 0.3
    #: candidates verified per keyframe, the most similar in appearance first.
    max_candidates: int = 4
    #: RANSAC iterations of the global registration (FPFH feature matches).
    ransac_iterations: int = 100000
    #: RANSAC's confidence: it stops early once this sure of its best pose.
    ransac_confidence: float = 0.999
    #: global registrations per candidate, each from its own seed; checked: enough RANSAC inliers, highest fitness
    ransac_restarts: int = 1
    #: feature matches that RANSAC's coarse pose must agree with, at least.
    min_inliers: int = 40
    #: fraction of the keyframe's downsampled points with a candidate point within a voxel after G-ICP, at least.
    min_fitness: float = 0.62
    #: metres: RMS distance of those point pairs, at most.
    max_inlier_rmse_m: float = 0.02
    #: a loop's difference from odometry within this chi-square (6 dof) quantile of its and odometry's uncertainty
    correction_confidence: float = 0.999
    #: the loop's point-to-plane information per point along its weakest direction, at least (1/3 a box; 0 a wall)
    min_constraint: float = 0.05
    #: a loop constrained less than min_constraint along its weakest direction: reject, or free (kept without it)
    weak_direction: WeakDirection = WeakDirection.reject
    #: metres: G-ICP is restarted this far either side of a loop's pose along its weakest direction (0: not)
    uniqueness_displacement_m: float = 0.02
    #: metres: those restarts must converge this close to the loop's pose, else it is not unique (the scene slides)
    uniqueness_tolerance_m: float = 0.015
    #: consecutive keyframes registered again with colour (coloured ICP), taking a slide it finds (null: if registered)
    colour_odometry: bool | None = method_setting(None)
    #: only an edge constrained less than this along its weakest direction is registered again (as min_constraint)
    colour_max_constraint: float = 0.04
    #: metres: coloured ICP's pose moving further than this across the edge's weakest direction is not taken
    colour_max_across_m: float = 0.005
    #: degrees: nor one turning it by more than this
    colour_max_turn_deg: float = 0.5
    #: metres: nor one moving it further than this along the weakest direction
    colour_max_slide_m: float = 0.10
    #: metres: nor one moving it less than this along it (as short as coloured ICP's own error)
    colour_min_slide_m: float = 0.01
    #: the pose-graph optimiser: gtsam | open3d.
    backend: Backend = Backend.gtsam
    #: metres: standard deviation of an odometry edge along its best-constrained direction.
    odometry_sigma_m: float = 0.005
    #: metres: standard deviation of a loop edge along its best-constrained direction.
    loop_sigma_m: float = 0.01
    #: whitened residual at which a loop edge's robust kernel halves its weight (gtsam: Cauchy; open3d: pruned there)
    robust_width: float = 3.0
    #: a new loop enters the graph only if, optimised with it, every edge's chi-square (6 dof) is below this quantile
    consistency_confidence: float = 0.999
    #: an optimised loop's whitened residual (sqrt chi-square) above which it is dropped and the graph solved again
    max_loop_residual: float = 10.0
    #: seed of RANSAC's random choices.
    seed: int = 0

    def validate(self) -> None:
        for name in ("voxel", "search_radius_m", "odometry_sigma_m", "loop_sigma_m", "robust_width",
                     "max_loop_residual", "max_inlier_rmse_m", "uniqueness_tolerance_m", "colour_max_across_m",
                     "colour_max_turn_deg", "colour_max_slide_m", "colour_max_constraint"):
            require(getattr(self, name) > 0, f"loop_closure.{name}", "> 0", getattr(self, name))
        for name in ("min_path_m", "radius_per_path", "min_constraint", "uniqueness_displacement_m",
                     "colour_min_slide_m"):
            require(getattr(self, name) >= 0, f"loop_closure.{name}", ">= 0", getattr(self, name))
        require(self.colour_min_slide_m < self.colour_max_slide_m, "loop_closure.colour_min_slide_m",
                f"below colour_max_slide_m ({self.colour_max_slide_m})", self.colour_min_slide_m)
        require(self.exclude_recent >= 1, "loop_closure.exclude_recent", "an integer >= 1", self.exclude_recent)
        require(0 < self.max_view_angle_deg <= 180, "loop_closure.max_view_angle_deg", "in (0, 180]",
                self.max_view_angle_deg)
        require(-1 <= self.min_appearance <= 1, "loop_closure.min_appearance", "in [-1, 1]", self.min_appearance)
        require(self.seed >= 0, "loop_closure.seed", "an integer >= 0", self.seed)
        require(self.max_candidates >= 1, "loop_closure.max_candidates", "an integer >= 1", self.max_candidates)
        require(self.ransac_iterations >= 1, "loop_closure.ransac_iterations", "an integer >= 1",
                self.ransac_iterations)
        require(self.ransac_restarts >= 1, "loop_closure.ransac_restarts", "an integer >= 1", self.ransac_restarts)
        require(0 < self.ransac_confidence < 1, "loop_closure.ransac_confidence", "in (0, 1)", self.ransac_confidence)
        require(self.min_inliers >= 3, "loop_closure.min_inliers", "an integer >= 3", self.min_inliers)
        require(0 < self.consistency_confidence < 1, "loop_closure.consistency_confidence", "in (0, 1)",
                self.consistency_confidence)
        require(0 < self.correction_confidence < 1, "loop_closure.correction_confidence", "in (0, 1)",
                self.correction_confidence)
        require(0 < self.min_fitness <= 1, "loop_closure.min_fitness", "in (0, 1]", self.min_fitness)

    def resolve(self, context: RunContext) -> PoseGraphConfig:
        # colour read at a point that is not the point's (7-Scenes) pulls coloured ICP off (docs/loop_closure.md)
        return self.fill_nulls(colour_odometry=context.tuning.colour_registered)
