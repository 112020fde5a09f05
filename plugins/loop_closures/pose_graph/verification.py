"""Geometric verification of a loop candidate: global registration of the keyframe's points in
the candidate's frame (FPFH + RANSAC, then G-ICP: `slamkit.geometry.registration`), accepted
only when every figure passes its bound (`PoseGraphConfig`): RANSAC's inliers, G-ICP's fitness
and inlier RMSE, agreement with odometry within a bound that grows with the camera path between
the two (a registration that snapped to a similar-looking other place lands far from where
odometry says), and a point-to-plane information that constrains every translation direction
(a wall alone lets the pose slide).
"""

from __future__ import annotations

import numpy as np

from slamkit.geometry.registration import FeatureCloud, alignment_information, register
from slamkit.roles.loop_closure import LoopCheck, pose_difference
from slamkit_plugins.loop_closures.pose_graph.config import PoseGraphConfig


def normalised_information(source: FeatureCloud, target: FeatureCloud, pose: np.ndarray,
                           max_distance: float) -> tuple[np.ndarray, int]:
    """(point-to-plane information of the alignment per matched point, matched points): its
    translation block's eigenvalues are the fractions of the matched normals along each
    direction (they sum to 1)."""
    info, matched = alignment_information(source, target, pose, max_distance)
    return info / max(matched, 1), matched


def verify(query: FeatureCloud, match: FeatureCloud, odometry: np.ndarray, path_m: float, cfg: PoseGraphConfig,
           ids: tuple[int, int, int, int], seed: int) -> tuple[LoopCheck, np.ndarray]:
    """The check of candidate `match` for keyframe `query` and the loop edge's information
    (6x6, in the query's frame, scaled by 1 / loop_sigma_m^2).

    odometry: the query's pose in the match's camera frame from the current estimates.
    path_m: metres of camera path between them. ids: (keyframe id, match id, frame index,
    match frame index)."""
    found = register(query, match, cfg.ransac_iterations, cfg.ransac_confidence, seed)
    if not np.isfinite(found.pose).all():  # G-ICP diverged (degenerate covariances): no pose to check
        failed = LoopCheck(*ids, relative_pose=np.eye(4), fitness=0.0, inliers=found.ransac_inliers,
                           inlier_rmse_m=0.0, correction_m=float("nan"), correction_deg=float("nan"), accepted=False,
                           reason="registration diverged (non-finite pose)")
        return failed, np.zeros((6, 6))
    correction_m, correction_deg = pose_difference(odometry, found.pose)
    information, _ = normalised_information(query, match, found.pose, cfg.voxel)
    check = LoopCheck(*ids, relative_pose=found.pose, fitness=found.fitness, inliers=found.ransac_inliers,
                      inlier_rmse_m=found.rmse_m, correction_m=correction_m, correction_deg=correction_deg,
                      accepted=True)
    bound_m = cfg.max_correction_m + cfg.correction_per_path * path_m
    bound_deg = cfg.max_correction_deg + cfg.correction_deg_per_path * path_m
    weakest = float(np.linalg.eigvalsh(information[3:, 3:])[0])
    failures = [
        (found.ransac_inliers < cfg.min_inliers, f"{found.ransac_inliers} RANSAC inliers < {cfg.min_inliers}"),
        (found.fitness < cfg.min_fitness, f"fitness {found.fitness:.3f} < {cfg.min_fitness}"),
        (found.rmse_m > cfg.max_inlier_rmse_m, f"inlier RMSE {found.rmse_m:.4f} m > {cfg.max_inlier_rmse_m}"),
        (correction_m > bound_m, f"{correction_m:.3f} m from odometry > {bound_m:.3f}"),
        (correction_deg > bound_deg, f"{correction_deg:.2f} deg from odometry > {bound_deg:.2f}"),
        (weakest < cfg.min_constraint, f"weakest direction constrained {weakest:.3f} < {cfg.min_constraint}"),
    ]
    reason = next((why for failed, why in failures if failed), "")
    return (check.rejected(reason) if reason else check), information / cfg.loop_sigma_m**2
