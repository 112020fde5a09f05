"""loops.csv: every loop candidate a run's loop closure verified, one row each, in the order they
were verified, with the columns of `slamkit.run.loop_closing.LOOPS_COLUMNS`: the two frames and
keyframes, the verification's figures (fitness, RANSAC inliers, inlier RMSE in metres), the
correction from odometry (metres, degrees), the relative pose found (translation in metres,
quaternion w, x, y, z: the keyframe's pose in the match's camera frame), whether the loop is in
the final pose graph and, if not, why."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, Sequence

from slamkit.formats.atomic import write_atomic


def write_loops_csv(path: str | Path, columns: Sequence[str], rows: list[dict[str, Any]]) -> None:
    """Write `rows` (dicts keyed by `columns`) to `path` atomically, a header first."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: row.get(k) for k in columns})
    write_atomic(path, text.getvalue())
