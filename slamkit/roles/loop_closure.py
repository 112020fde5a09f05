"""The loop-closure role: finds where the camera came back to a place an earlier keyframe saw,
and corrects the keyframes' poses so that the trajectory agrees with it.

Pure algorithm, no threads and no files: the run gives each keyframe (`add_keyframe`), asks for
a decision now and then (`detect_and_optimise`), and applies it: each keyframe's pose, and what
the keyframe placed in the world (its Gaussians, the frames tracked from it: `follow_keyframes`),
moves by the decision's `updates`. The run writes `loops()` as loops.csv (`LoopCheck.row`) and
`pose_graph()` as g2o (`slamkit.formats.g2o`). The pose graph's types and how frames follow their
keyframes are geometry (`slamkit.geometry.pose_graph`), re-exported here.

Frames and units: poses are 4x4 float64 camera-to-world, metres. A relative pose from keyframe i
to keyframe j is inv(T_i) @ T_j, the pose of j in i's camera frame. An information matrix is
6x6 in (rotation radians, translation metres) order, for a small motion exp(xi) applied on the
right of the relative pose (in j's camera frame), as gtsam's Pose3 and g2o's SE3 edges (after
reordering) take it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np

from slamkit.geometry.pose_graph import PoseGraph, PoseGraphEdge, follow_keyframes, pose_difference, relative_pose
from slamkit.geometry.pose_graph import check_argument as _check
from slamkit.geometry.transforms import rotmat_to_quat

# The pose graph's types and relations are part of the role's contract: a plugin imports them here.
__all__ = ["LoopCheck", "LoopClosure", "LoopDecision", "LoopKeyframe", "PoseGraph", "PoseGraphEdge",
           "follow_keyframes", "pose_difference", "relative_pose"]


@dataclass(frozen=True)
class LoopKeyframe:
    """One keyframe as loop closure sees it.

    keyframe_id: the run's keyframe number (0, 1, ... in the order given; the id its Gaussians
    carry in the map). frame_index: the frame it was made from (`Frame.index`). pose: 4x4
    camera-to-world as tracked, in the world of the last decision the run applied (the tracker
    follows the corrected map). points: (N,3) the keyframe's Gaussian centres (or depth points)
    in its camera frame, metres. covariances: (N,3,3) their covariances in the camera frame, m^2
    (G-ICP's), or None (estimated from the points' normals). image: (h,w,3) uint8 colour image
    of any size, for appearance, or None. odometry_information: 6x6 information of the relative
    pose from the previous keyframe to this one (see the module docstring), or None (the loop
    closure computes one from the two keyframes' points). world: the `LoopDecision.world` of the
    last decision the run had applied when it tracked this keyframe (0 before any; always 0
    while the run holds the decisions to the end of the stream, `loop_corrections=at_end`): a
    keyframe tracked in an older world is placed in the newest by the loop closure. colours:
    (N,3) the points' RGB in [0, 1], or None.
    """

    keyframe_id: int
    frame_index: int
    pose: np.ndarray
    points: np.ndarray
    covariances: np.ndarray | None = None
    image: np.ndarray | None = None
    odometry_information: np.ndarray | None = None
    world: int = 0
    colours: np.ndarray | None = None

    def __post_init__(self) -> None:
        pose = np.asarray(self.pose, dtype=np.float64)
        _check(pose.shape == (4, 4) and bool(np.isfinite(pose).all()), "LoopKeyframe.pose",
               "a finite 4x4 camera-to-world matrix", self.pose)
        object.__setattr__(self, "pose", pose)
        points = np.asarray(self.points)
        _check(points.ndim == 2 and points.shape[1] == 3, "LoopKeyframe.points", "an (N,3) array", points)
        if self.covariances is not None:
            _check(np.shape(self.covariances) == (len(points), 3, 3), "LoopKeyframe.covariances",
                   f"({len(points)},3,3), one per point", np.asarray(self.covariances))
        if self.colours is not None:
            _check(np.shape(self.colours) == (len(points), 3), "LoopKeyframe.colours",
                   f"({len(points)},3), one RGB per point", np.asarray(self.colours))
        if self.image is not None:
            _check(np.ndim(self.image) == 3 and np.shape(self.image)[2] == 3, "LoopKeyframe.image",
                   "an (h,w,3) colour image", np.asarray(self.image))
        if self.odometry_information is not None:
            _check(np.shape(self.odometry_information) == (6, 6), "LoopKeyframe.odometry_information", "6x6",
                   np.asarray(self.odometry_information))


@dataclass(frozen=True)
class LoopCheck:
    """One candidate pair, verified: keyframe `keyframe_id` (frame `frame_index`) seen again
    from earlier keyframe `match_id` (frame `match_frame_index`).

    relative_pose: the pose of the keyframe in the match's camera frame that registration found
    (4x4; identity when registration failed). fitness: the fraction of the keyframe's
    downsampled points with a match point within one voxel after refinement. inliers: the
    feature matches RANSAC's pose agreed with. inlier_rmse_m: RMS distance of the fitness's
    point pairs. correction_m, correction_deg: how far `relative_pose` is from the odometry's
    relative pose (inv(T_match) @ T_keyframe as tracked), translation and angle. accepted: the
    loop is a constraint of the pose graph. reason: why it was left, or why it was kept (a loop
    closure may leave it "" when accepted).
    """

    keyframe_id: int
    match_id: int
    frame_index: int
    match_frame_index: int
    relative_pose: np.ndarray
    fitness: float
    inliers: int
    inlier_rmse_m: float
    correction_m: float
    correction_deg: float
    accepted: bool
    reason: str = ""

    #: The columns of loops.csv, in order (`row`).
    COLUMNS = ("frame", "match_frame", "keyframe", "match_keyframe", "fitness", "inliers", "inlier_rmse_m",
               "correction_m", "correction_deg", "tx", "ty", "tz", "qw", "qx", "qy", "qz")

    def row(self) -> dict[str, Any]:
        """loops.csv's row: frames and keyframes, the verification's figures, the correction,
        and `relative_pose` as translation (metres) and quaternion (w, x, y, z)."""
        q = rotmat_to_quat(self.relative_pose[:3, :3])
        values = (self.frame_index, self.match_frame_index, self.keyframe_id, self.match_id, self.fitness, self.inliers,
                  self.inlier_rmse_m, self.correction_m, self.correction_deg, *self.relative_pose[:3, 3], *q)
        return dict(zip(self.COLUMNS, (v.item() if isinstance(v, np.generic) else v for v in values)))

    def rejected(self, reason: str) -> LoopCheck:
        """This check, not accepted, for `reason`."""
        return replace(self, accepted=False, reason=reason)


@dataclass(frozen=True)
class LoopDecision:
    """What one `detect_and_optimise` call found and did.

    checks: every candidate pair it verified, accepted or not (a loop the optimiser found
    inconsistent with the others is listed as rejected). keyframe_poses: keyframe id -> its
    corrected 4x4 camera-to-world pose, for every keyframe of the graph when a loop moved them;
    empty when nothing moved. updates: keyframe id -> 4x4 world-frame rigid motion from the
    keyframe's previous pose (the last one reported, or the one it was added with) to the
    corrected one: corrected = update @ previous; what the keyframe placed in the world (its
    Gaussians' means and rotations, frames tracked from it) moves by the same update; so do
    the keyframes added after the last one listed (`follow_keyframes`). world: how many
    decisions have moved keyframes, this one included (the run gives it back in
    `LoopKeyframe.world` once it has applied this decision).
    """

    checks: tuple[LoopCheck, ...] = ()
    keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)
    updates: dict[int, np.ndarray] = field(default_factory=dict)
    world: int = 0

    @property
    def accepted(self) -> tuple[LoopCheck, ...]:
        """The loops accepted in this call."""
        return tuple(c for c in self.checks if c.accepted)

    def __bool__(self) -> bool:
        """True when keyframes moved."""
        return bool(self.updates)


class LoopClosure(ABC):
    """Detects loops among keyframes and corrects their poses (see the module docstring).

    `closes_loops`: False for a loop closure that never moves a keyframe (`none`): the run then
    gives it no keyframes and starts no thread for it."""

    closes_loops: ClassVar[bool] = True

    @abstractmethod
    def add_keyframe(self, keyframe: LoopKeyframe) -> None:
        """Take a new keyframe (ids increase). Cheap: detection waits for `detect_and_optimise`."""

    @abstractmethod
    def detect_and_optimise(self) -> LoopDecision:
        """Look for loops from the keyframes added since the last call, verify them, and when
        one is accepted optimise the pose graph; the decision says what moved."""

    def loops(self) -> list[LoopCheck]:
        """Every loop accepted so far and still in the pose graph, in the order accepted."""
        return []

    def pose_graph(self) -> PoseGraph:
        """The current pose graph (nodes, odometry and loop edges)."""
        return PoseGraph(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))

    def state_dict(self) -> dict[str, Any]:
        """What this loop closure needs to go on where a run stopped (saved in the map
        checkpoint): JSON values and numpy arrays. {} by default."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()`, before the next keyframe. Nothing by default."""
