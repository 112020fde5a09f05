"""loops.csv: every loop candidate a run's loop closure verified, one row each, in the order they
were verified, with the columns of `slamkit.run.loop_closing.LOOPS_COLUMNS`: the two frames and
keyframes, the verification's figures (fitness, RANSAC inliers, inlier RMSE in metres), the
correction from odometry (metres, degrees), the relative pose found (translation in metres,
quaternion w, x, y, z: the keyframe's pose in the match's camera frame), whether the loop is in
the final pose graph and why it was kept or left, and, when the dataset has ground truth, how far
the loop's relative pose is from the ground truth's (`gt_error_m`, `gt_error_deg`; empty without)."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from slamkit.formats.atomic import write_atomic
from slamkit.geometry.pose_graph import pose_difference
from slamkit.geometry.transforms import make_pose, nearest_rotation, quat_to_rotmat

#: The ground-truth columns `with_ground_truth` adds.
GROUND_TRUTH_COLUMNS = ("gt_error_m", "gt_error_deg")


def with_ground_truth(row: dict[str, Any], gt_pose: np.ndarray | None, gt_match_pose: np.ndarray | None) -> dict:
    """loops.csv's `row` with `gt_error_m` (metres) and `gt_error_deg` (degrees): the difference
    between its relative pose (tx..qz) and the ground truth's, inv(gt_match_pose) @ gt_pose (4x4
    camera-to-world each, of the keyframe and of its match); None for both without ground truth.
    The ground truth's rotations are re-orthonormalised first: 7-Scenes' pose files are off by
    ~1e-4, which alone reads as ~1 degree of relative rotation."""
    error: tuple[float | None, float | None] = (None, None)
    if gt_pose is not None and gt_match_pose is not None and np.isfinite(gt_pose).all() \
            and np.isfinite(gt_match_pose).all():
        gt = np.array([gt_pose, gt_match_pose], dtype=np.float64)
        gt[:, :3, :3] = nearest_rotation(gt[:, :3, :3])
        truth = np.linalg.inv(gt[1]) @ gt[0]
        found = make_pose(quat_to_rotmat(np.array([row[k] for k in ("qw", "qx", "qy", "qz")], dtype=np.float64)),
                          np.array([row[k] for k in ("tx", "ty", "tz")], dtype=np.float64))
        error = pose_difference(truth, found)
    return {**row, **dict(zip(GROUND_TRUTH_COLUMNS, error))}


def write_loops_csv(path: str | Path, columns: Sequence[str], rows: list[dict[str, Any]]) -> None:
    """Write `rows` (dicts keyed by `columns`) to `path` atomically, a header first."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: row.get(k) for k in columns})
    write_atomic(path, text.getvalue())
