"""Odometry edges measured again with colour (`colour_odometry`).

Where the geometry pins a keyframe only weakly along one direction (a wall and the floor leave the
line along both free), the tracker's depth-only G-ICP can slide along it, pushed by the depth
noise: the synthetic room_loop's drift is a few such slides between consecutive keyframes
(docs/loop_closure.md, "Odometry's slides, measured with colour"). A striped wall, a picture, a
radiator still pin that direction in colour. Each new keyframe's points are registered again in
the previous keyframe's frame by coloured ICP (`slamkit.geometry.registration.refine_coloured`),
from the tracked relative pose, where the edge is weakly constrained (its point-to-plane
information per point along its weakest translation direction below `colour_max_constraint`, the
measure of `min_constraint`: 0 for a wall alone, 1/3 for a box); the odometry edge takes the
result only when it moves the pose along that direction and hardly otherwise: within
`colour_max_across_m` across it, `colour_max_turn_deg` of rotation, and at least
`colour_min_slide_m` and at most `colour_max_slide_m` along it (a shorter slide is as large as
coloured ICP's own error, and taking it swaps one error for another). Coloured ICP alone, taken
whole, sends some edges a metre away (scenes whose colour gradients pull it off the overlap), and
on well-constrained edges it is the less accurate of the two: the geometry is trusted where it is
strong.
"""

from __future__ import annotations

import numpy as np

from slamkit.geometry.registration import FeatureCloud, refine_coloured
from slamkit.roles.loop_closure import pose_difference
from slamkit_plugins.loop_closures.pose_graph.config import PoseGraphConfig


def coloured_odometry(cloud: FeatureCloud, previous: FeatureCloud, relative: np.ndarray, per_point: np.ndarray,
                      cfg: PoseGraphConfig) -> np.ndarray:
    """The relative pose the odometry edge from `previous` to `cloud` takes: the pose of `cloud`'s
    keyframe in `previous`'s camera frame (4x4, metres), coloured ICP's from the tracked
    `relative` when the edge is weakly constrained along its weakest direction and coloured ICP
    only slides along that one, by `colour_min_slide_m` to `colour_max_slide_m`, else
    `relative` itself. `per_point`: the edge's point-to-plane information per matched point at
    `relative` (`normalised_information`). Both clouds need colours."""
    values, vectors = np.linalg.eigh(per_point[3:, 3:])
    if values[0] >= cfg.colour_max_constraint:
        return relative  # where the geometry pins the pose, colour only adds its own errors
    found = refine_coloured(cloud, previous, relative)
    if not np.isfinite(found).all():
        return relative
    weakest = relative[:3, :3] @ vectors[:, 0]  # in the previous keyframe's frame, as the translations
    moved = found[:3, 3] - relative[:3, 3]
    along = float(moved @ weakest)
    across = float(np.linalg.norm(moved - along * weakest))
    turn = pose_difference(relative, found)[1]
    if across > cfg.colour_max_across_m or turn > cfg.colour_max_turn_deg or abs(along) > cfg.colour_max_slide_m:
        return relative  # not a slide: colour pulled elsewhere, where the geometry disagrees
    if abs(along) < cfg.colour_min_slide_m:
        return relative  # a slide as short as the registrations' own errors: nothing to correct
    return found
