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

`OdometryEdges` holds the graph's odometry edges and measures them: an edge between coloured
clouds is measured with colour only when the graph is next read, so a sequence with no loop
candidate runs no coloured ICP at all, and a checkpoint runs none under the map's lock.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from slamkit.geometry.registration import FeatureCloud, refine_coloured
from slamkit.roles.loop_closure import PoseGraphEdge, pose_difference
from slamkit_plugins.loop_closures.pose_graph import verification
from slamkit_plugins.loop_closures.pose_graph.config import PoseGraphConfig

#: An odometry edge's information until it is measured (`OdometryEdges.measured`): NaN, which
#: `PoseGraphLoopClosure.pose_graph` refuses, so that an edge read before then fails rather than
#: optimising with a made-up weight (the optimisers would take NaN silently).
_UNMEASURED = np.full((6, 6), np.nan)
_UNMEASURED.setflags(write=False)


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


class OdometryEdges:
    """The pose graph's odometry edges, edge k from keyframe k to keyframe k + 1: the tracked
    relative pose (with colours, moved by a slide coloured ICP finds: `coloured_odometry`) and
    the keyframe's information, or where it has none the point-to-plane information of the two
    clouds under the edge (per matched point, over odometry_sigma_m^2)."""

    def __init__(self, cfg: PoseGraphConfig):
        self.cfg = cfg
        self._edges: list[PoseGraphEdge] = []
        # edges joined with colours, in `_edges` still as tracked, to be measured before they are
        # read: index -> (the previous keyframe's cloud, the keyframe's, its information or None)
        self._unmeasured: dict[int, tuple[FeatureCloud, FeatureCloud, np.ndarray | None]] = {}

    def join(self, previous_id: int, previous: FeatureCloud, keyframe_id: int, cloud: FeatureCloud,
             relative: np.ndarray, information: np.ndarray | None) -> None:
        """Add the edge from keyframe `previous_id` (its `previous` cloud) to `keyframe_id` (its
        `cloud`): `relative`, the tracked pose of the keyframe in the previous one's camera frame
        (4x4, metres); `information`, the keyframe's own (6x6, rotation first) or None."""
        if cloud.cloud.has_colors() and previous.cloud.has_colors():
            self._unmeasured[len(self._edges)] = (previous, cloud, information)
            self._edges.append(PoseGraphEdge("odometry", previous_id, keyframe_id, relative, _UNMEASURED))
        else:
            self._edges.append(self._measure(previous_id, previous, keyframe_id, cloud, relative, information))

    def measured(self) -> list[PoseGraphEdge]:
        """The edges, in order, every one measured (those joined with colours are measured now)."""
        for index in sorted(self._unmeasured):  # one at a time: a registration that raises leaves the rest
            previous, cloud, information = self._unmeasured[index]
            edge = self._edges[index]
            self._edges[index] = self._measure(edge.source, previous, edge.target, cloud, edge.relative_pose,
                                               information)
            del self._unmeasured[index]
        return list(self._edges)

    def _measure(self, previous_id: int, previous: FeatureCloud, keyframe_id: int, cloud: FeatureCloud,
                 relative: np.ndarray, information: np.ndarray | None) -> PoseGraphEdge:
        """The edge from `previous_id` to `keyframe_id`, measured (see the class)."""
        cfg = self.cfg
        coloured = cloud.cloud.has_colors() and previous.cloud.has_colors()
        if information is None or coloured:
            per_point, _ = verification.normalised_information(cloud, previous, relative, cfg.voxel)
            if coloured:
                found = coloured_odometry(cloud, previous, relative, per_point, cfg)
                if found is not relative and information is None:  # moved: its information where it now is
                    per_point, _ = verification.normalised_information(cloud, previous, found, cfg.voxel)
                relative = found
        if information is None:
            information = (per_point + verification.INFORMATION_FLOOR * np.eye(6)) / cfg.odometry_sigma_m**2
        return PoseGraphEdge("odometry", previous_id, keyframe_id, relative, np.asarray(information, dtype=np.float64))

    # -- checkpoints --------------------------------------------------------------------------

    def state_dict(self) -> list[dict[str, Any]]:
        """The edges, an edge not yet measured with colour kept so (`"measured": false`, with the
        keyframe's information or None): a checkpoint runs no coloured ICP."""
        return [{"kind": e.kind, "source": e.source, "target": e.target, "relative_pose": e.relative_pose,
                 "information": self._unmeasured[k][2] if k in self._unmeasured else e.information,
                 "measured": k not in self._unmeasured} for k, e in enumerate(self._edges)]

    def load_state_dict(self, edges: list[dict[str, Any]], clouds: dict[int, FeatureCloud]) -> None:
        """Restore the edges of `state_dict` (a checkpoint without `"measured"`: all measured);
        `clouds`: keyframe id -> its cloud."""
        self._edges, self._unmeasured = [], {}
        for e in edges:
            source, target = int(e["source"]), int(e["target"])
            relative = np.asarray(e["relative_pose"], dtype=np.float64)
            information = None if e["information"] is None else np.asarray(e["information"], dtype=np.float64)
            if e.get("measured", True):
                self._edges.append(PoseGraphEdge("odometry", source, target, relative, information))
            else:
                self._unmeasured[len(self._edges)] = (clouds[source], clouds[target], information)
                self._edges.append(PoseGraphEdge("odometry", source, target, relative, _UNMEASURED))
