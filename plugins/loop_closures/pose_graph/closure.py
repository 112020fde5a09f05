"""The pose-graph loop closure: keyframes are the graph's nodes, consecutive keyframes are tied
by odometry edges, verified loops add loop edges, and each accepted loop re-optimises the graph.

Per `detect_and_optimise` call, for each keyframe added since the last one, in order:
1. it joins the graph: its points are downsampled with FPFH features (`FeatureCloud`), and an
   odometry edge from the previous keyframe holds the tracked relative pose (with
   `colour_odometry`, moved by a slide coloured ICP finds, measured when the graph is next
   read: `odometry.OdometryEdges`), weighted by the keyframe's information or the point-to-plane
   information of the two keyframes' points under it;
2. candidates: earlier keyframes (not the last `exclude_recent`, at least `min_path_m` of path
   back) near its place and similar in appearance (`detection`), at most `max_candidates`;
3. each is verified (`verification`); a loop that passes is tried in the graph (`_consistent`):
   the graph is optimised with it, and it stays only if every edge, odometry and loop alike,
   is then within the chi-square test (`consistency_confidence`); otherwise it is left out, and
   the graph is as it was. A kept loop is a loop edge (information over loop_sigma_m^2), robust
   in the optimiser. loops.csv's reason says which test kept or left each candidate.
Then, if a loop was accepted, the graph is optimised (`optimisation`); a loop whose whitened
residual stays above `max_loop_residual` is taken out as inconsistent and the graph optimised
again without it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from slamkit.config import RunContext
from slamkit.geometry.pose_graph import chain_covariances
from slamkit.geometry.registration import FeatureCloud, import_open3d
from slamkit.roles.loop_closure import (
    LoopCheck,
    LoopClosure,
    LoopDecision,
    LoopKeyframe,
    PoseGraph,
    PoseGraphEdge,
    relative_pose,
)
from slamkit_plugins.loop_closures.pose_graph import detection, odometry, optimisation, verification
from slamkit_plugins.loop_closures.pose_graph.config import Backend, PoseGraphConfig

#: Optimise-and-drop rounds at most per decision (each drops the worst inconsistent loop).
MAX_DROP_ROUNDS = 10


@dataclass
class _Node:
    """A keyframe in the graph. pose: its current camera-to-world estimate (the world of the
    latest decision). median_depth: metres, of its points (its place, `detection`)."""

    keyframe_id: int
    frame_index: int
    pose: np.ndarray
    cloud: FeatureCloud
    descriptor: np.ndarray | None
    median_depth: float


def _refused(check: LoopCheck, why: str) -> LoopCheck:
    """`check` refused by the graph for `why`; a freed loop keeps its mark after it (a benchmark
    leaves the freed direction out of the loop's error)."""
    mark = verification.freed_mark(check.reason)
    return check.rejected(f"{why}; {mark}" if mark else why)


class PoseGraphLoopClosure(LoopClosure):
    """Loop detection by place and appearance, geometric verification, pose-graph optimisation."""

    def __init__(self, cfg: PoseGraphConfig, context: RunContext = RunContext()):
        cfg = self.cfg = cfg.resolve(context)
        import_open3d()  # the libraries it needs, now: a missing one fails here, in one line
        if cfg.backend is Backend.gtsam:
            optimisation.import_gtsam()
        self.nodes: list[_Node] = []
        self.odometry = odometry.OdometryEdges(cfg)
        self.loop_edges: list[PoseGraphEdge] = []  # in the order they joined
        self.accepted: list[LoopCheck] = []  # in the graph, in the order of loop_edges
        self.pending: list[LoopKeyframe] = []
        self.world = 0
        self.world_updates: list[np.ndarray] = []  # per decision that moved keyframes: its last keyframe's update

    # -- the role -----------------------------------------------------------------------------

    def add_keyframe(self, keyframe: LoopKeyframe) -> None:
        last = self.pending[-1].keyframe_id if self.pending else self.nodes[-1].keyframe_id if self.nodes else None
        if last is not None and keyframe.keyframe_id <= last:
            raise ValueError(f"LoopKeyframe.keyframe_id: expected ids that increase, got {keyframe.keyframe_id} "
                             f"after {last}")
        if not 0 <= keyframe.world <= self.world:
            raise ValueError(f"LoopKeyframe.world: expected 0 to {self.world} (decisions made), got {keyframe.world}")
        self.pending.append(keyframe)

    def detect_and_optimise(self) -> LoopDecision:
        checks: list[LoopCheck] = []
        pending, self.pending = self.pending, []
        for keyframe in pending:
            self._join(keyframe)
            checks += self._detect(len(self.nodes) - 1)
        if not any(c.accepted for c in checks):
            return LoopDecision(tuple(checks), world=self.world)
        before = {n.keyframe_id: n.pose for n in self.nodes}  # as last reported, or as joined
        dropped = self._optimise()
        this_call = {(c.keyframe_id, c.match_id) for c in checks}
        checks = [dropped.pop((c.keyframe_id, c.match_id)) if (c.keyframe_id, c.match_id) in dropped else c
                  for c in checks]
        checks += [c for key, c in dropped.items() if key not in this_call]  # loops of earlier calls, now dropped
        updates = {n.keyframe_id: n.pose @ np.linalg.inv(before[n.keyframe_id]) for n in self.nodes}
        moved = any(not np.allclose(u, np.eye(4), atol=1e-12) for u in updates.values())
        if not moved:
            return LoopDecision(tuple(checks), world=self.world)
        self.world += 1
        self.world_updates.append(updates[self.nodes[-1].keyframe_id])
        return LoopDecision(tuple(checks), {n.keyframe_id: n.pose.copy() for n in self.nodes}, updates, self.world)

    def loops(self) -> list[LoopCheck]:
        return list(self.accepted)

    def pose_graph(self) -> PoseGraph:
        edges = self._edges()
        if not all(np.isfinite(e.information).all() for e in edges):
            raise RuntimeError("PoseGraphLoopClosure.pose_graph: an edge's information is not finite")
        ids = np.array([n.keyframe_id for n in self.nodes], dtype=np.int64)
        poses = np.array([n.pose for n in self.nodes]).reshape(-1, 4, 4)
        return PoseGraph(ids, poses, tuple(edges))

    def _edges(self) -> list[PoseGraphEdge]:
        """Every edge, measured, in the order they joined: each keyframe's odometry edge, then
        the loops found from it (the order fixes the optimisers' and pose_graph.g2o's)."""
        order = {n.keyframe_id: k for k, n in enumerate(self.nodes)}
        return sorted(self.odometry.measured() + self.loop_edges, key=lambda e: (order[e.target], e.kind == "loop"))

    # -- the steps ----------------------------------------------------------------------------

    def _join(self, keyframe: LoopKeyframe) -> None:
        """Add `keyframe` as a node (its pose brought into the current world) with its odometry edge."""
        pose = keyframe.pose
        for update in self.world_updates[keyframe.world:]:
            pose = update @ pose
        cfg = self.cfg
        colours = keyframe.colours if cfg.colour_odometry else None
        cloud = FeatureCloud(keyframe.points, cfg.voxel, keyframe.covariances, colours)
        depth = float(np.median(np.asarray(keyframe.points)[:, 2])) if len(keyframe.points) else 0.0
        descriptor = None if keyframe.image is None else detection.appearance_descriptor(keyframe.image)
        node = _Node(keyframe.keyframe_id, keyframe.frame_index, pose, cloud, descriptor, depth)
        if self.nodes:
            previous = self.nodes[-1]
            self.odometry.join(previous.keyframe_id, previous.cloud, node.keyframe_id, cloud,
                               relative_pose(previous.pose, pose), keyframe.odometry_information)
        self.nodes.append(node)

    def _path(self) -> np.ndarray:
        """(K,) metres of camera path from the first keyframe to each (current estimates)."""
        centres = np.array([n.pose[:3, 3] for n in self.nodes])
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))])

    def _detect(self, query: int) -> list[LoopCheck]:
        """Verify the candidates of node `query`; accepted loops join the graph as loop edges."""
        cfg = self.cfg
        path = self._path()
        eligible = np.arange(max(query - cfg.exclude_recent, 0))
        eligible = eligible[path[query] - path[eligible] >= cfg.min_path_m]
        poses = np.array([n.pose for n in self.nodes])
        depths = np.array([n.median_depth for n in self.nodes])
        near = detection.place_candidates(poses, depths, path, query, eligible, cfg.search_radius_m,
                                          cfg.radius_per_path, cfg.max_view_angle_deg)
        node = self.nodes[query]
        if node.descriptor is not None:
            similarity = {int(j): float(self.nodes[j].descriptor @ node.descriptor) for j in near
                          if self.nodes[j].descriptor is not None}
            near = sorted((j for j in similarity if similarity[j] >= cfg.min_appearance), key=lambda j: -similarity[j])
        checks = []
        candidates = list(near)[:cfg.max_candidates]
        uncertainty = self._odometry_uncertainty(query) if candidates else None
        for j in candidates:
            match = self.nodes[j]
            ids = (node.keyframe_id, match.keyframe_id, node.frame_index, match.frame_index)
            tracked = relative_pose(match.pose, node.pose)
            check, information = verification.verify(node.cloud, match.cloud, tracked, uncertainty[j], cfg, ids,
                                                     cfg.seed + node.keyframe_id)
            if check.accepted:
                check = self._consistent(check, PoseGraphEdge("loop", match.keyframe_id, node.keyframe_id,
                                                              check.relative_pose, information))
            checks.append(check)
        return checks

    def _odometry_uncertainty(self, query: int) -> np.ndarray:
        """(query, 6, 6): element j is the covariance of odometry's relative pose from node j to
        node `query` (in the query's frame), accumulated along the odometry edges between them."""
        edges = self.odometry.measured()[:query]  # edge k ends at node k + 1
        poses = np.array([e.relative_pose for e in edges]).reshape(-1, 4, 4)
        covariances = np.linalg.inv(np.array([e.information for e in edges]).reshape(-1, 6, 6))
        return chain_covariances(poses, covariances)

    def _consistent(self, check: LoopCheck, edge: PoseGraphEdge) -> LoopCheck:
        """`check` (verified) with its reason: its loop `edge` joins the graph when, optimised
        with it, every edge's chi-square (squared whitened residual, 6 degrees of freedom) is
        within the `consistency_confidence` quantile: the loop agrees with odometry and the
        loops already there. A wrong loop that passed verification bends the graph, and the
        edges it bends (or itself, when the robust kernel lets it go) fail; a right one's
        correction spreads over the odometry edges within their noise. Else the edge is left out."""
        self.loop_edges.append(edge)
        graph = self.pose_graph()
        chi2 = optimisation.whitened_residuals(graph, optimisation.optimise(graph, self.cfg.backend,
                                                                             self.cfg.robust_width)) ** 2
        bound = optimisation.chi_square_6_quantile(self.cfg.consistency_confidence)
        worst = {kind: max(((float(c), e) for c, e in zip(chi2, graph.edges) if e.kind == kind),
                           key=lambda pair: pair[0], default=(0.0, None)) for kind in ("odometry", "loop")}
        figures = ", ".join(f"{kind} {c:.1f}" for kind, (c, _) in worst.items())
        failed = [(c, e) for c, e in worst.values() if c > bound]
        if failed:
            self.loop_edges.pop()
            c, e = failed[0]
            return _refused(check, f"inconsistent with the graph: {e.kind} edge {e.source}->{e.target} chi-square "
                                   f"{c:.1f} > {bound:.1f} once optimised with it (largest: {figures})")
        why = f"consistent: largest chi-square once optimised with it: {figures} <= {bound:.1f}"
        kept = replace(check, reason=f"{why}; {check.reason}" if check.reason else why)
        self.accepted.append(kept)
        return kept

    def _optimise(self) -> dict[tuple[int, int], LoopCheck]:
        """Optimise the graph, dropping inconsistent loops one at a time; the nodes take the
        optimised poses. Returns (keyframe id, match id) -> its check, rejected with the reason,
        for each loop dropped."""
        dropped: dict[tuple[int, int], LoopCheck] = {}
        for _ in range(MAX_DROP_ROUNDS):
            graph = self.pose_graph()
            poses = optimisation.optimise(graph, self.cfg.backend, self.cfg.robust_width)
            residuals = optimisation.whitened_residuals(graph, poses)
            loops = [i for i, e in enumerate(graph.edges) if e.kind == "loop"]
            worst = max(loops, key=lambda i: residuals[i], default=None)
            if worst is None or residuals[worst] <= self.cfg.max_loop_residual:
                break
            edge = graph.edges[worst]
            self.loop_edges = [e for e in self.loop_edges if e is not edge]
            key = (edge.target, edge.source)
            check = next(c for c in self.accepted if (c.keyframe_id, c.match_id) == key)
            self.accepted.remove(check)
            dropped[key] = _refused(check, f"inconsistent with the pose graph: whitened residual "
                                           f"{residuals[worst]:.1f} > {self.cfg.max_loop_residual}")
        else:
            graph = self.pose_graph()
            poses = optimisation.optimise(graph, self.cfg.backend, self.cfg.robust_width)
        for node, pose in zip(self.nodes, poses):
            node.pose = pose
        return dropped

    # -- checkpoints --------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        if self.pending:  # a keyframe not yet in the graph would need its raw points: join it first
            raise ValueError("PoseGraphLoopClosure.state_dict: keyframes are pending; call detect_and_optimise first")
        nodes = [{"keyframe_id": n.keyframe_id, "frame_index": n.frame_index, "pose": n.pose,
                  "median_depth": n.median_depth, "descriptor": n.descriptor, "cloud": n.cloud.arrays()}
                 for n in self.nodes]
        edges = self.odometry.state_dict() + [
            {"kind": e.kind, "source": e.source, "target": e.target, "relative_pose": e.relative_pose,
             "information": e.information} for e in self.loop_edges]
        loops = [{**c.row(), "relative_pose": c.relative_pose, "reason": c.reason} for c in self.accepted]
        return {"nodes": nodes, "edges": edges, "loops": loops, "world": self.world,
                "world_updates": list(self.world_updates)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        voxel = self.cfg.voxel
        self.nodes = [_Node(int(n["keyframe_id"]), int(n["frame_index"]), np.asarray(n["pose"], dtype=np.float64),
                            FeatureCloud.from_arrays(n["cloud"], voxel),
                            None if n["descriptor"] is None else np.asarray(n["descriptor"], dtype=np.float32),
                            float(n["median_depth"])) for n in state["nodes"]]
        self.odometry.load_state_dict([e for e in state["edges"] if e["kind"] == "odometry"],
                                      {n.keyframe_id: n.cloud for n in self.nodes})
        self.loop_edges = [PoseGraphEdge("loop", int(e["source"]), int(e["target"]),
                                         np.asarray(e["relative_pose"], dtype=np.float64),
                                         np.asarray(e["information"], dtype=np.float64))
                           for e in state["edges"] if e["kind"] == "loop"]
        self.accepted = [LoopCheck(int(c["keyframe"]), int(c["match_keyframe"]), int(c["frame"]),
                                   int(c["match_frame"]), np.asarray(c["relative_pose"], dtype=np.float64),
                                   float(c["fitness"]), int(c["inliers"]), float(c["inlier_rmse_m"]),
                                   float(c["correction_m"]), float(c["correction_deg"]), True, str(c["reason"]))
                         for c in state["loops"]]
        self.world = int(state["world"])
        self.world_updates = [np.asarray(u, dtype=np.float64) for u in state["world_updates"]]
        self.pending = []
