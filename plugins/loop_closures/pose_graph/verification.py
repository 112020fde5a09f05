"""Geometric verification of a loop candidate: global registration of the keyframe's points in
the candidate's frame (FPFH + RANSAC, then G-ICP: `slamkit.geometry.registration`; with
`ransac_restarts`, the best of several draws), accepted
only when every figure passes its bound (`PoseGraphConfig`): RANSAC's inliers, G-ICP's fitness
and inlier RMSE, agreement with odometry within the uncertainty odometry accumulated between the
two keyframes and the loop's own (a chi-square test: a registration that snapped to a
similar-looking other place lands far from where odometry says, unless tracking slid there),
a point-to-plane information that constrains every translation direction (a wall alone
lets the pose slide), and, last, a pose that is unique: G-ICP restarted a little either side of
it along its weakest direction comes back to it (`sliding`: a repeated structure can hold a
registration 10 cm off that every other figure accepts).
"""

from __future__ import annotations

import re

import numpy as np

from slamkit.geometry.registration import FeatureCloud, alignment_information, refine, register
from slamkit.geometry.transforms import se3_exp, so3_log
from slamkit.roles.loop_closure import LoopCheck, pose_difference, relative_pose
from slamkit_plugins.loop_closures.pose_graph.config import PoseGraphConfig, WeakDirection
from slamkit_plugins.loop_closures.pose_graph.optimisation import chi_square_6_quantile

#: Added to a point-to-plane information per matched point, so that a direction the points do
#: not constrain (or a pair with no matched points) keeps a finite uncertainty: 1/sqrt(this) =
#: ~30 times the edge's sigma.
INFORMATION_FLOOR = 1e-3
#: What a freed direction keeps of a loop's information per matched point: enough for gtsam to
#: factorise it (an exactly singular one is factorised unchecked), 1000 times the loop's sigma;
#: not the floor, whose ~30 sigma still pulls where odometry is weak along the same wall
#: (docs/loop_closure.md, "A loop's weakest direction freed").
FREED_INFORMATION = 1e-6
#: A restart's seed is the candidate's plus this times its number: no other keyframe's (seed + id) meets it.
RESTART_SEED_STRIDE = 1_000_003
#: How loops.csv's reason marks a loop kept without its weakest direction (`freed_reason`), and that direction.
FREED_MARK = re.compile(r"freed along \(([-+0-9.]+), ([-+0-9.]+), ([-+0-9.]+)\): constrained [^\s;]+ < [^\s;]+")


def freed_reason(direction: np.ndarray, constrained: float, bound: float) -> str:
    """The mark of a loop kept without its weakest `direction` (unit, the keyframe's camera
    frame), constrained `constrained` < `bound` along it (`FREED_MARK` reads it back)."""
    along = ", ".join(f"{c:+.3f}" for c in direction)
    return f"freed along ({along}): constrained {max(constrained, 0.0):.3f} < {bound}"


def freed_mark(reason: str) -> str:
    """The part of a loop's `reason` that says it was freed along a direction, or ""."""
    found = FREED_MARK.search(reason)
    return found.group(0) if found else ""


def freed_direction(reason: str) -> np.ndarray | None:
    """(3,) the unit direction (keyframe's camera frame) a loop's `reason` says it was freed
    along, or None."""
    found = FREED_MARK.search(reason)
    if not found:
        return None
    direction = np.array([float(x) for x in found.groups()])
    return direction / np.linalg.norm(direction)


def without_component(translations: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(..., 3) `translations` with their component along the unit `direction` removed."""
    translations = np.asarray(translations, dtype=np.float64)
    return translations - (translations @ direction)[..., None] * direction


def normalised_information(source: FeatureCloud, target: FeatureCloud, pose: np.ndarray,
                           max_distance: float) -> tuple[np.ndarray, int]:
    """(point-to-plane information of the alignment per matched point, matched points): its
    translation block's eigenvalues are the fractions of the matched normals along each
    direction (they sum to 1)."""
    info, matched = alignment_information(source, target, pose, max_distance)
    return info / max(matched, 1), matched


def restarts(query: FeatureCloud, match: FeatureCloud, pose: np.ndarray, starts: np.ndarray,
             freed: np.ndarray | None = None) -> np.ndarray:
    """(S, 2): how far (metres, degrees) G-ICP converges from `pose` (the query's pose in the
    match's frame) when started at pose @ exp(xi) for each of the (S, 6) `starts` xi ((rotation
    rad, translation m), in the query's frame). A pose the scene pins down draws every start back
    to it; one the scene lets slide (a corridor, a repeated structure) keeps them where they
    started, or sends them elsewhere. `freed` (a unit translation in the query's frame): a
    direction the loop leaves free, not counted in the distance."""
    converged = [refine(query, match, pose @ se3_exp(xi)).pose for xi in np.asarray(starts, dtype=np.float64)]
    away = np.array([relative_pose(pose, found) for found in converged]).reshape(-1, 4, 4)
    if freed is not None:
        away[:, :3, 3] = without_component(away[:, :3, 3], freed)
    return np.array([pose_difference(np.eye(4), d) for d in away]).reshape(-1, 2)


def sliding(query: FeatureCloud, match: FeatureCloud, pose: np.ndarray, weakest: np.ndarray, displacement_m: float,
            tolerance_m: float, freed: np.ndarray | None = None) -> str:
    """Whether the registration's `pose` (the query's in the match's frame) is unique: "" when G-ICP
    restarted `displacement_m` either side of it along `weakest` (a unit translation in the
    query's frame: the alignment's least constrained direction; with `freed`, the direction the
    loop leaves free, the least constrained of the others, and drift along `freed` not counted)
    comes back within `tolerance_m` both times; else, as loops.csv's reason, the restart that did not. A scene
    that lets the pose slide (repeated structure, a corridor) leaves the restarts where they
    started or sends them elsewhere; measured, the right loops' restarts came back within
    1.3 cm from 2 cm, the wrong ones' ended 1.9-4.6 cm away (docs/loop_closure.md)."""
    offsets = displacement_m * np.array([1.0, -1.0])
    starts = np.concatenate([np.zeros((2, 3)), offsets[:, None] * weakest], axis=1)
    away = restarts(query, match, pose, starts, freed)
    worst = int(np.argmax(away[:, 0]))
    if away[worst, 0] <= tolerance_m:
        return ""
    name = "weakest" if freed is None else "second-weakest"
    return (f"not unique: from {100 * offsets[worst]:+.1f} cm along its {name} direction G-ICP converged "
            f"{100 * away[worst, 0]:.1f} cm, {away[worst, 1]:.2f} deg away > {100 * tolerance_m:.1f} cm")


def marginalised(information: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """`information` (6x6) with the 6-vector `direction` (unit) unknown: its Schur complement, the
    information on every other direction once the pose along `direction` may be anything. It
    leaves `direction` in its null space, and the covariance of the other directions is that of
    `information`'s: a rotation the loop pinned only through its coupling with `direction` is
    freed with it (projecting `direction` out would keep that information)."""
    coupling = information @ direction
    along = float(direction @ coupling)
    if along <= 1e-12 * max(float(np.trace(information)), 1e-300):  # nothing along it: nothing to free
        return information
    return information - np.outer(coupling, coupling) / along


def verify(query: FeatureCloud, match: FeatureCloud, odometry: np.ndarray, odometry_covariance: np.ndarray,
           cfg: PoseGraphConfig, ids: tuple[int, int, int, int], seed: int) -> tuple[LoopCheck, np.ndarray]:
    """The check of candidate `match` for keyframe `query` and the loop edge's information
    (6x6, in the query's frame, scaled by 1 / loop_sigma_m^2).

    odometry: the query's pose in the match's camera frame from the current estimates.
    odometry_covariance: 6x6, the uncertainty of `odometry` accumulated along the odometry edges
    between them (`slamkit.geometry.pose_graph.chain_covariances`).
    ids: (keyframe id, match id, frame index, match frame index)."""
    # RANSAC's draws decide a long revisit: a pair registers right from some seeds and centimetres to
    # a metre off from others, and the right pose has the highest fitness (docs/loop_closure.md);
    # a draw whose RANSAC found too few inliers is last (G-ICP from its identity can fit well)
    found = max((register(query, match, cfg.ransac_iterations, cfg.ransac_confidence, seed + k * RESTART_SEED_STRIDE)
                 for k in range(cfg.ransac_restarts)),
                key=lambda registration: (registration.ransac_inliers >= cfg.min_inliers, registration.fitness))
    if not np.isfinite(found.pose).all():  # G-ICP diverged (degenerate covariances): no pose to check
        failed = LoopCheck(*ids, relative_pose=np.eye(4), fitness=0.0, inliers=found.ransac_inliers,
                           inlier_rmse_m=0.0, correction_m=float("nan"), correction_deg=float("nan"), accepted=False,
                           reason="registration diverged (non-finite pose)")
        return failed, np.zeros((6, 6))
    correction_m, correction_deg = pose_difference(odometry, found.pose)
    information, _ = normalised_information(query, match, found.pose, cfg.voxel)
    fractions, directions = np.linalg.eigh(information[3:, 3:])
    weakest = float(fractions[0])
    free_weakest = weakest < cfg.min_constraint and cfg.weak_direction is WeakDirection.free
    # loops.csv says which loops were kept without their weakest direction (the closure adds why it kept them)
    kept_as = freed_reason(directions[:, 0], weakest, cfg.min_constraint) if free_weakest else ""
    check = LoopCheck(*ids, relative_pose=found.pose, fitness=found.fitness, inliers=found.ransac_inliers,
                      inlier_rmse_m=found.rmse_m, correction_m=correction_m, correction_deg=correction_deg,
                      accepted=True, reason=kept_as)
    if free_weakest:
        # a wall seen again pins the pose across it but not along it: keep what it pins, and let
        # the graph place the pose along the weakest direction (a registration may have slid there)
        along = np.concatenate([np.zeros(3), directions[:, 0]])
        information = marginalised(information, along) + FREED_INFORMATION * np.outer(along, along)
    # the loop's difference from odometry, whitened by both uncertainties: odometry's, accumulated
    # along the path (large where tracking slid along a wall), and the loop's own
    loop_covariance = cfg.loop_sigma_m**2 * np.linalg.inv(information + INFORMATION_FLOOR * np.eye(6))
    difference = relative_pose(odometry, found.pose)
    xi = np.concatenate([so3_log(difference[:3, :3]), difference[:3, 3]])
    chi2 = float(xi @ np.linalg.solve(odometry_covariance + loop_covariance, xi))
    bound = chi_square_6_quantile(cfg.correction_confidence)
    failures = [
        (found.ransac_inliers < cfg.min_inliers, f"{found.ransac_inliers} RANSAC inliers < {cfg.min_inliers}"),
        (found.fitness < cfg.min_fitness, f"fitness {found.fitness:.3f} < {cfg.min_fitness}"),
        (found.rmse_m > cfg.max_inlier_rmse_m, f"inlier RMSE {found.rmse_m:.4f} m > {cfg.max_inlier_rmse_m}"),
        (chi2 > bound, f"{correction_m:.3f} m, {correction_deg:.2f} deg from odometry: chi-square {chi2:.1f} > "
                       f"{bound:.1f} of their uncertainties"),
        (weakest < cfg.min_constraint and not free_weakest,
         f"weakest direction constrained {weakest:.3f} < {cfg.min_constraint}"),
        # one direction is all a loop may leave to the graph: a wall alone leaves two
        (free_weakest and fractions[1] < cfg.min_constraint,
         f"second-weakest direction constrained {fractions[1]:.3f} < {cfg.min_constraint}"),
    ]
    reason = next((why for failed, why in failures if failed), "")
    if not reason and cfg.uniqueness_displacement_m > 0:  # the costlier test last: only a loop that passed the rest
        # unique along the weakest direction the loop constrains
        reason = sliding(query, match, found.pose, directions[:, 1 if free_weakest else 0],
                         cfg.uniqueness_displacement_m, cfg.uniqueness_tolerance_m,
                         directions[:, 0] if free_weakest else None)
    # a freed loop refused keeps its mark after why (a benchmark leaves its freed direction out of its error)
    refused = f"{reason}; {kept_as}" if kept_as else reason
    return (check.rejected(refused) if reason else check), information / cfg.loop_sigma_m**2
