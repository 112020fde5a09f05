"""The g2o text format of a 3D pose graph (`slamkit.roles.loop_closure.PoseGraph`), as g2o,
gtsam (`gtsam.readG2o(path, True)`) and common pose-graph tools read it:

    VERTEX_SE3:QUAT id tx ty tz qx qy qz qw
    EDGE_SE3:QUAT source target tx ty tz qx qy qz qw  I11 I12 .. I16 I22 .. I66

A vertex is a keyframe (its id) and its camera-to-world pose; an edge the pose of `target` in
`source`'s camera frame and the upper triangle of its 6x6 information matrix in g2o's
(translation, rotation) order, the rotation rows per radian as gtsam reads them. Quaternions are
(x, y, z, w) here only; slamkit's are (w, x, y, z). An edge between consecutive vertices (in
file order) reads back as odometry, any other as a loop.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.geometry.pose_graph import PoseGraph, PoseGraphEdge
from slamkit.geometry.transforms import make_pose, quat_to_rotmat, rotmat_to_quat

VERTEX, EDGE = "VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"
#: slamkit's (rotation, translation) order to g2o's (translation, rotation), and back (its own inverse).
_REORDER = np.array([3, 4, 5, 0, 1, 2])
_UPPER = np.triu_indices(6)


def _pose_fields(pose: np.ndarray) -> list[float]:
    w, x, y, z = rotmat_to_quat(pose[:3, :3])
    return [*pose[:3, 3], x, y, z, w]


def _fmt(values) -> str:
    return " ".join(f"{v:.17g}" for v in values)


def to_g2o(graph: PoseGraph) -> str:
    """The pose graph as g2o text (module docstring)."""
    lines = [f"{VERTEX} {int(k)} {_fmt(_pose_fields(p))}" for k, p in zip(graph.keyframe_ids, graph.poses)]
    for e in graph.edges:
        info = np.asarray(e.information, dtype=np.float64)[np.ix_(_REORDER, _REORDER)]
        lines.append(f"{EDGE} {int(e.source)} {int(e.target)} {_fmt(_pose_fields(e.relative_pose))} "
                     f"{_fmt(info[_UPPER])}")
    return "\n".join(lines) + "\n"


def _pose(values: list[float]) -> np.ndarray:
    tx, ty, tz, qx, qy, qz, qw = values
    return make_pose(quat_to_rotmat(np.array([qw, qx, qy, qz])), np.array([tx, ty, tz]))


def read_g2o(path: Path) -> PoseGraph:
    """The pose graph of a g2o file written by `to_g2o` (other tags are refused). DataError
    naming the file and line for anything else."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read {path}: {str(exc).splitlines()[0]}") from None
    ids, poses, raw_edges = [], [], []
    for no, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        expected = {VERTEX: 9, EDGE: 31}.get(fields[0])
        if expected is None or len(fields) != expected:
            raise DataError(f"{path}:{no}: expected {VERTEX} with 8 fields or {EDGE} with 30, "
                            f"got {line.strip()[:60]!r}")
        try:
            values = [float(v) for v in fields[1:]]
        except ValueError:
            raise DataError(f"{path}:{no}: expected numbers, got {line.strip()[:60]!r}") from None
        if not np.all(np.isfinite(values)) or values[0] != int(values[0]):
            raise DataError(f"{path}:{no}: expected finite numbers and integer ids, got {line.strip()[:60]!r}")
        if fields[0] == VERTEX:
            ids.append(int(values[0]))
            poses.append(_pose(values[1:]))
        else:
            info = np.zeros((6, 6))
            info[_UPPER] = values[9:]
            info = info + np.triu(info, 1).T
            raw_edges.append((int(values[0]), int(values[1]), _pose(values[2:9]), info[np.ix_(_REORDER, _REORDER)]))
    following = dict(zip(ids, ids[1:]))
    edges = tuple(PoseGraphEdge("odometry" if following.get(s) == t else "loop", s, t, T, info)
                  for s, t, T, info in raw_edges)
    return PoseGraph(np.array(ids, dtype=np.int64), np.array(poses).reshape(-1, 4, 4), edges)
