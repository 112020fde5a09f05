"""Pose-graph optimisation with a well-kept library: keyframe poses are the nodes, the first one
held fixed; odometry edges are Gaussian, loop edges robust. Two backends (`Backend`), chosen by
measurement (docs/loop_closure.md):

- gtsam: Levenberg-Marquardt over Pose3 with BetweenFactorPose3 edges; loops under a Cauchy
  kernel whose weight halves at a whitened residual of `robust_width`.
- open3d: `global_optimization` (Levenberg-Marquardt, Choi et al. 2015's line process on the
  loop edges, which prunes a loop whose weight falls below 1/4, at a whitened residual of
  `robust_width`).

Both take the information matrices as slamkit states them (`slamkit.roles.loop_closure`):
(rotation, translation) order, for a motion on the right of the relative pose, which is the
convention of gtsam's Pose3 and of open3d's pose-graph edges (from the edge's source node,
our edge's target).
"""

from __future__ import annotations

import numpy as np

from slamkit.errors import SlamkitError
from slamkit.geometry.registration import import_open3d
from slamkit.geometry.transforms import so3_log
from slamkit.roles.loop_closure import PoseGraph, relative_pose
from slamkit_plugins.loop_closures.pose_graph.config import Backend

#: Standard deviation (metres and radians) of the prior that holds the first keyframe in place.
ANCHOR_SIGMA = 1e-6


def import_gtsam():
    """gtsam, or a one-line SlamkitError saying how to install it."""
    try:
        import gtsam
    except ImportError as exc:
        raise SlamkitError(f"gtsam is not installed ({exc}); install it with pip install -e '.[loop]'") from None
    return gtsam


def whitened_residuals(graph: PoseGraph, poses: np.ndarray) -> np.ndarray:
    """(E,) sqrt(e^T Info e) of each edge at `poses` ((K,4,4) in `graph.keyframe_ids` order),
    e = (rotation vector, translation) of inv(measured) @ inv(T_source) @ T_target."""
    if not graph.edges:
        return np.zeros(0)
    index = {int(k): i for i, k in enumerate(graph.keyframe_ids)}
    src = poses[[index[e.source] for e in graph.edges]]
    dst = poses[[index[e.target] for e in graph.edges]]
    measured = np.stack([e.relative_pose for e in graph.edges])
    error = relative_pose(measured, relative_pose(src, dst))
    e = np.concatenate([so3_log(error[:, :3, :3]), error[:, :3, 3]], axis=1)
    info = np.stack([e.information for e in graph.edges])
    return np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", e, info, e), 0.0))


def chi_square_6_quantile(confidence: float) -> float:
    """x with P(chi-square, 6 degrees of freedom <= x) = confidence, for confidence in (0, 1).
    The distribution's survival function has a closed form for an even number of degrees of
    freedom, exp(-x/2) (1 + x/2 + (x/2)^2 / 2), decreasing in x: bisection finds x to 1e-9."""
    lo, hi = 0.0, 1000.0
    for _ in range(100):
        x = 0.5 * (lo + hi)
        h = 0.5 * x
        lo, hi = (x, hi) if np.exp(-h) * (1.0 + h + 0.5 * h * h) > 1.0 - confidence else (lo, x)
    return 0.5 * (lo + hi)


def optimise(graph: PoseGraph, backend: Backend, robust_width: float) -> np.ndarray:
    """(K,4,4) optimised camera-to-world poses of `graph`'s nodes (its poses are the start)."""
    if len(graph.keyframe_ids) < 2 or not graph.edges:
        return np.array(graph.poses, dtype=np.float64)
    if backend is Backend.gtsam:
        return _optimise_gtsam(graph, robust_width)
    return _optimise_open3d(graph, robust_width)


def _optimise_gtsam(graph: PoseGraph, robust_width: float) -> np.ndarray:
    gtsam = import_gtsam()
    factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, pose in zip(graph.keyframe_ids, graph.poses):
        values.insert(int(k), gtsam.Pose3(np.asarray(pose, dtype=np.float64)))
    factors.add(gtsam.PriorFactorPose3(int(graph.keyframe_ids[0]), gtsam.Pose3(graph.poses[0]),
                                       gtsam.noiseModel.Isotropic.Sigma(6, ANCHOR_SIGMA)))
    kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(robust_width)
    for e in graph.edges:
        noise = gtsam.noiseModel.Gaussian.Information(np.asarray(e.information, dtype=np.float64))
        if e.kind == "loop":
            noise = gtsam.noiseModel.Robust.Create(kernel, noise)
        factors.add(gtsam.BetweenFactorPose3(int(e.source), int(e.target), gtsam.Pose3(e.relative_pose), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(factors, values, params).optimize()
    return np.stack([result.atPose3(int(k)).matrix() for k in graph.keyframe_ids])


def _optimise_open3d(graph: PoseGraph, robust_width: float) -> np.ndarray:
    o3d = import_open3d()
    reg = o3d.pipelines.registration
    index = {int(k): i for i, k in enumerate(graph.keyframe_ids)}
    pose_graph = reg.PoseGraph()
    for pose in graph.poses:
        pose_graph.nodes.append(reg.PoseGraphNode(np.asarray(pose, dtype=np.float64)))
    for e in graph.edges:
        pose_graph.edges.append(reg.PoseGraphEdge(index[e.target], index[e.source], np.asarray(e.relative_pose),
                                                  np.asarray(e.information), uncertain=e.kind == "loop"))
    # The line process's weight is preference * distance^2 * mean(Info[5,5]) (open3d assumes the
    # information counts correspondences); this distance makes it robust_width^2, in whitened units.
    mean_z_information = float(np.mean([e.information[5, 5] for e in graph.edges]))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=robust_width / np.sqrt(mean_z_information),
                                          edge_prune_threshold=0.25, preference_loop_closure=1.0, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(pose_graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    return np.stack([np.asarray(n.pose) for n in pose_graph.nodes])
