"""A pose graph of keyframes (nodes: camera-to-world poses; edges: relative-pose constraints
with their information), and how the frames tracked from a keyframe follow it when it moves.

Frames and units: poses are 4x4 float64 camera-to-world, metres. A relative pose from keyframe i
to keyframe j is inv(T_i) @ T_j, the pose of j in i's camera frame. An information matrix is
6x6 in (rotation radians, translation metres) order, for a small motion exp(xi) applied on the
right of the relative pose (in j's camera frame), as gtsam's Pose3 and g2o's SE3 edges (after
reordering) take it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from slamkit.geometry.transforms import invert_pose, rotation_angle_deg, skew


def check_argument(condition: bool, what: str, expected: str, value: Any) -> None:
    """ValueError naming `what`, what was expected and the value (or its shape) unless `condition`."""
    if not condition:
        shape = getattr(value, "shape", None)
        raise ValueError(f"{what}: expected {expected}, got {shape if shape is not None else value!r}")


@dataclass(frozen=True)
class PoseGraphEdge:
    """A relative-pose constraint between keyframes `source` and `target` (keyframe ids).
    kind: "odometry" (consecutive keyframes, from tracking) or "loop". relative_pose: 4x4, the
    measured pose of `target` in `source`'s camera frame. information: 6x6 (module docstring)."""

    kind: str
    source: int
    target: int
    relative_pose: np.ndarray
    information: np.ndarray


@dataclass(frozen=True)
class PoseGraph:
    """keyframe_ids: (K,) ids of the nodes. poses: (K,4,4) their current camera-to-world poses.
    edges: the constraints, odometry first then loops in the order accepted."""

    keyframe_ids: np.ndarray
    poses: np.ndarray
    edges: tuple[PoseGraphEdge, ...] = ()


def follow_keyframes(poses: np.ndarray, frame_indices: np.ndarray, keyframe_frames: np.ndarray,
                     updates: np.ndarray) -> np.ndarray:
    """Poses moved with their keyframes: each frame keeps its pose relative to the last keyframe
    at or before it (frames before the first keyframe follow the first).

    poses: (F,4,4) camera-to-world of frames `frame_indices` ((F,) `Frame.index`).
    keyframe_frames: (K,) increasing frame indices of the keyframes. updates: (K,4,4) each
    keyframe's world-frame motion (`LoopDecision.updates`). Returns (F,4,4): updates[k] @ pose.
    """
    poses = np.asarray(poses, dtype=np.float64)
    keyframe_frames = np.asarray(keyframe_frames)
    check_argument(len(keyframe_frames) == len(updates) and len(keyframe_frames) > 0, "follow_keyframes",
           "one update per keyframe, at least one keyframe", (len(keyframe_frames), len(updates)))
    check_argument(bool(np.all(np.diff(keyframe_frames) > 0)), "follow_keyframes keyframe_frames", "increasing indices",
           keyframe_frames)
    return np.asarray(updates, dtype=np.float64)[owning_keyframes(frame_indices, keyframe_frames)] @ poses


def owning_keyframes(indices: np.ndarray, keyframe_indices: np.ndarray) -> np.ndarray:
    """(F,) positions in `keyframe_indices` ((K,) increasing, K >= 1) of the last keyframe at or
    before each of `indices` (the first keyframe for those before it): whose correction a frame
    (or a Gaussian, by the keyframe id it carries) follows."""
    return np.clip(np.searchsorted(np.asarray(keyframe_indices), np.asarray(indices), side="right") - 1, 0, None)


def relative_pose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The pose of camera-to-world `b` in `a`'s camera frame, inv(a) @ b ((...,4,4))."""
    return invert_pose(a) @ b


def pose_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two 4x4 poses: the translation and angle of inv(a) @ b."""
    d = relative_pose(a, b)
    return float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d[:3, :3]))


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of the 4x4 pose `T` in (rotation, translation) order: a motion exp(xi) on the
    right of T equals exp(adjoint(T) @ xi) on its left, [[R, 0], [skew(t) R, R]]."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = R
    out[3:, :3] = skew(t) @ R
    return out


def chain_covariances(relative_poses: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """(N,6,6): element i is the covariance (module docstring's order and side) of the composed
    relative pose relative_poses[i] @ ... @ relative_poses[-1], given the (N,4,4) motions' own
    (N,6,6) covariances, independent, to first order: each motion's error is carried into the
    last frame by the adjoint of the inverse of the motions after it."""
    out = np.zeros((len(relative_poses), 6, 6))
    total, after = np.zeros((6, 6)), np.eye(4)
    for i in range(len(relative_poses) - 1, -1, -1):
        carry = adjoint(invert_pose(after))
        total = total + carry @ covariances[i] @ carry.T
        out[i] = total
        after = relative_poses[i] @ after
    return out
