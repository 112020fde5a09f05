"""The TUM RGB-D file formats: list files, trajectories, timestamp association, interpolation.

- List file (rgb.txt, depth.txt): ``timestamp filename`` per line, ``#`` comments.
- Trajectory (groundtruth.txt, a run's trajectory.txt): ``timestamp tx ty tz qx qy qz qw`` per
  line; translation in metres, camera-to-world. TUM writes quaternions (x, y, z, w); slamkit
  uses (w, x, y, z) everywhere else, and the conversion happens only in this module.

Timestamps are seconds (float64). Poses are 4x4 float64 camera-to-world.
Bad input raises `slamkit.errors.DataError` naming the file and the line.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.formats.atomic import write_atomic
from slamkit.geometry.transforms import quat_to_rotmat, rotmat_to_quat


def _data_lines(path: Path, commas: bool = True):
    """(line number, fields) of each non-empty, non-comment line of a text file; fields are
    separated by whitespace (and commas where `commas`)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        reason = "file not found" if isinstance(exc, FileNotFoundError) else str(exc).splitlines()[0]
        raise DataError(f"cannot read {path}: {reason}") from None
    for no, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#"):
            yield no, (line.replace(",", " ") if commas else line).split()


def _to_float(path: Path, no: int, s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise DataError(f"{path} line {no}: {s!r} is not a number") from None
    if not math.isfinite(v):
        raise DataError(f"{path} line {no}: {s!r} is not a finite number")
    return v


def read_float_table(path: str | Path, columns: int, expected: str) -> np.ndarray:
    """Rows x `columns` float64 array of a whitespace-separated text file (``#`` comments).

    A line with another field count or a non-finite / non-numeric field raises DataError
    naming the file, the line and `expected` (e.g. "16 numbers: a row-major 4x4 pose")."""
    path = Path(path)
    rows = []
    for no, f in _data_lines(path):
        if len(f) != columns:
            raise DataError(f"{path} line {no}: {len(f)} fields (expected {expected})")
        rows.append([_to_float(path, no, s) for s in f])
    return np.array(rows, dtype=np.float64).reshape(-1, columns)


def _sorted_unique(path: Path, ts: np.ndarray, what: str) -> np.ndarray:
    """Stable sort order of `ts`; DataError for a duplicate timestamp."""
    order = np.argsort(ts, kind="stable")
    s = ts[order]
    dup = np.flatnonzero(np.diff(s) == 0)
    if len(dup):
        raise DataError(f"{path}: timestamp {s[dup[0]]:.6f} appears twice (expected one {what} per timestamp)")
    return order


def read_tum_list(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """(timestamps in seconds sorted ascending, file names as written) of a TUM list file.

    Out-of-order lines are sorted; a duplicate timestamp raises DataError."""
    path = Path(path)
    ts, names = [], []
    for no, f in _data_lines(path, commas=False):
        if len(f) != 2:
            raise DataError(f"{path} line {no}: {len(f)} fields (expected 'timestamp filename')")
        ts.append(_to_float(path, no, f[0]))
        names.append(f[1])
    ts = np.array(ts, dtype=np.float64)
    order = _sorted_unique(path, ts, "image")
    return ts[order], [names[i] for i in order]


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(N timestamps in seconds, ascending; Nx4x4 float64 camera-to-world poses) of a TUM
    trajectory file. Lines are sorted by time; a duplicate timestamp or a zero quaternion
    raises DataError."""
    path = Path(path)
    table = read_float_table(path, 8, "8 numbers: timestamp tx ty tz qx qy qz qw")
    order = _sorted_unique(path, table[:, 0], "pose")
    table = table[order]
    q_wxyz = table[:, [7, 4, 5, 6]]
    norm = np.linalg.norm(q_wxyz, axis=1)
    if np.any(norm < 1e-9):
        t = table[np.argmax(norm < 1e-9), 0]
        raise DataError(f"{path}: the pose at timestamp {t:.6f} has a zero quaternion (expected a unit quaternion)")
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :3] = quat_to_rotmat(q_wxyz) if len(table) else np.zeros((0, 3, 3))
    poses[:, :3, 3] = table[:, 1:4]
    return table[:, 0].copy(), poses


def write_tum_trajectory(path: str | Path, timestamps, poses) -> None:
    """Write camera-to-world 4x4 `poses` (N x 4 x 4, metres) at `timestamps` (N, seconds) as a
    TUM trajectory, atomically: a temporary file in the same folder, then os.replace."""
    path = Path(path)
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(ts) != len(poses):
        raise ValueError(f"{len(ts)} timestamps but {len(poses)} poses")
    if not (np.isfinite(ts).all() and np.isfinite(poses).all()):
        raise ValueError("timestamps and poses must be finite")
    q = rotmat_to_quat(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    table = np.column_stack([ts, poses[:, :3, 3], q[:, 1:], q[:, :1]])
    body = "".join(f"{r[0]:.6f} " + " ".join(f"{v:.9f}" for v in r[1:]) + "\n" for r in table)
    write_atomic(path, body)  # no header: exactly one line per frame (the run-output contract)


def associate(first: np.ndarray, second: np.ndarray, max_difference: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one association of two timestamp arrays (seconds), as TUM's associate.py does:
    among all pairs with |t1 - t2| < max_difference, greedily take the closest pair whose two
    members are both still free. Returns index arrays (into `first`, into `second`) sorted
    by the index into `first`."""
    a, b = np.asarray(first, dtype=np.float64), np.asarray(second, dtype=np.float64)
    ob = np.argsort(b, kind="stable")
    bs = b[ob]
    lo = np.searchsorted(bs, a - max_difference, side="left")
    hi = np.searchsorted(bs, a + max_difference, side="right")
    ia = np.repeat(np.arange(len(a)), hi - lo)
    offsets = np.arange(len(ia)) - np.repeat(np.cumsum(hi - lo) - (hi - lo), hi - lo)
    ib = ob[np.repeat(lo, hi - lo) + offsets]
    d = np.abs(a[ia] - b[ib])
    keep = d < max_difference
    ia, ib, d = ia[keep], ib[keep], d[keep]
    used_a, used_b = np.zeros(len(a), bool), np.zeros(len(b), bool)
    out_a, out_b = [], []
    for k in np.lexsort((ib, ia, d)):
        i, j = ia[k], ib[k]
        if not (used_a[i] or used_b[j]):
            used_a[i] = used_b[j] = True
            out_a.append(i)
            out_b.append(j)
    out_a, out_b = np.array(out_a, dtype=np.int64), np.array(out_b, dtype=np.int64)
    order = np.argsort(out_a)
    return out_a[order], out_b[order]


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical interpolation of (N,4) unit quaternions (w, x, y, z) at fractions (N,) in
    [0, 1], along the shorter arc."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    small = sin < 1e-8
    safe = np.where(small, 1.0, sin)
    w0 = np.where(small, 1 - alpha, np.sin((1 - alpha) * theta) / safe)
    w1 = np.where(small, alpha, np.sin(alpha * theta) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def interpolate_poses(
    timestamps: np.ndarray, poses: np.ndarray, query: np.ndarray, max_gap: float | None = None
) -> np.ndarray:
    """Poses (Q x 4 x 4) at `query` timestamps from a trajectory (`timestamps` ascending, N;
    `poses` N x 4 x 4 camera-to-world): linear in translation, slerp in rotation between the
    two samples around each query.

    A query outside [timestamps[0], timestamps[-1]], or whose nearest sample is farther than
    `max_gap` seconds (None = no limit), gets an all-NaN pose."""
    ts = np.asarray(timestamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64).reshape(-1)
    out = np.full((len(query), 4, 4), np.nan)
    if len(ts) == 0 or len(query) == 0:
        return out
    if len(ts) == 1:
        out[query == ts[0]] = poses[0]
        return out
    i1 = np.clip(np.searchsorted(ts, query, side="left"), 1, len(ts) - 1)
    i0 = i1 - 1
    t0, t1 = ts[i0], ts[i1]
    valid = (query >= ts[0]) & (query <= ts[-1])
    if max_gap is not None:
        valid &= np.minimum(np.abs(query - t0), np.abs(t1 - query)) <= max_gap
    i0, i1, t0, t1, q = i0[valid], i1[valid], t0[valid], t1[valid], query[valid]
    alpha = np.clip((q - t0) / (t1 - t0), 0.0, 1.0)
    rot = quat_to_rotmat(slerp(rotmat_to_quat(poses[i0, :3, :3]), rotmat_to_quat(poses[i1, :3, :3]), alpha))
    res = np.tile(np.eye(4), (len(q), 1, 1))
    res[:, :3, :3] = rot
    res[:, :3, 3] = (1 - alpha)[:, None] * poses[i0, :3, 3] + alpha[:, None] * poses[i1, :3, 3]
    out[valid] = res
    return out
