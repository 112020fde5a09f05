"""TUM file formats: list files, trajectories, association, interpolation."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from slamkit.errors import DataError
from slamkit.formats.tum import (
    associate,
    interpolate_poses,
    read_float_table,
    read_tum_list,
    read_tum_trajectory,
    write_tum_trajectory,
)
from slamkit.geometry.transforms import make_pose, quat_to_rotmat, rotation_angle_deg, so3_exp

from support.errors import one_line


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --- list files ---------------------------------------------------------------------------

def test_list_file_skips_comments_and_sorts(tmp_path):
    p = write(tmp_path / "rgb.txt", "# color images\n\n2.5 rgb/b.png\n1.0 rgb/a.png\n  # x\n3.0 rgb/c.png\n")
    ts, names = read_tum_list(p)
    assert ts.tolist() == [1.0, 2.5, 3.0]
    assert names == ["rgb/a.png", "rgb/b.png", "rgb/c.png"]


def test_list_file_duplicate_timestamp(tmp_path):
    p = write(tmp_path / "rgb.txt", "1.0 a.png\n2.0 b.png\n1.0 c.png\n")
    with pytest.raises(DataError) as e:
        read_tum_list(p)
    assert "1.000000" in one_line(e, "rgb.txt")


@pytest.mark.parametrize(
    "line, needle",
    [("1.0 a.png extra", "3 fields"), ("abc a.png", "'abc'"), ("nan a.png", "finite"), ("inf a.png", "finite")],
)
def test_list_file_bad_line_names_line(tmp_path, line, needle):
    p = write(tmp_path / "depth.txt", f"# header\n0.5 x.png\n{line}\n")
    with pytest.raises(DataError) as e:
        read_tum_list(p)
    msg = one_line(e, "depth.txt")
    assert "line 3" in msg and needle in msg


def test_missing_file(tmp_path):
    with pytest.raises(DataError) as e:
        read_tum_list(tmp_path / "nope.txt")
    assert "not found" in one_line(e, "nope.txt")


def test_float_table_field_count(tmp_path):
    p = write(tmp_path / "traj.txt", "1 2 3\n4 5\n")
    with pytest.raises(DataError) as e:
        read_float_table(p, 3, "3 numbers")
    assert "line 2" in one_line(e, "traj.txt")


# --- trajectories -------------------------------------------------------------------------

def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(n)])


def test_trajectory_round_trip(tmp_path):
    poses = random_poses(20)
    ts = 1305031229.528748 + np.arange(20) * 0.033
    path = tmp_path / "out" / "trajectory.txt"
    write_tum_trajectory(path, ts, poses)
    ts2, poses2 = read_tum_trajectory(path)
    np.testing.assert_allclose(ts2, ts, atol=1e-6)
    np.testing.assert_allclose(poses2, poses, atol=1e-7)
    assert [p.name for p in path.parent.iterdir()] == ["trajectory.txt"]  # no temp file left


def test_trajectory_quaternion_order_is_xyzw_in_file(tmp_path):
    Rz90 = quat_to_rotmat(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))  # (w, x, y, z)
    path = tmp_path / "t.txt"
    write_tum_trajectory(path, [0.0], make_pose(Rz90, [1, 2, 3])[None])
    fields = [float(v) for v in path.read_text().splitlines()[0].split()]
    np.testing.assert_allclose(fields, [0, 1, 2, 3, 0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)], atol=1e-9)
    assert len(path.read_text().splitlines()) == 1  # one line per pose, no header


def test_trajectory_write_replaces_existing(tmp_path):
    path = write(tmp_path / "t.txt", "old contents\n")
    write_tum_trajectory(path, [1.0, 2.0], random_poses(2))
    assert len(read_tum_trajectory(path)[0]) == 2
    assert sorted(os.listdir(tmp_path)) == ["t.txt"]


def test_trajectory_sorted_and_validated(tmp_path):
    p = write(tmp_path / "gt.txt", "2 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    ts, poses = read_tum_trajectory(p)
    assert ts.tolist() == [1.0, 2.0] and poses[0, 0, 3] == 1.0
    for bad, needle in [("1 0 0 0 0 0 0\n", "line 1"), ("1 0 0 0 0 0 0 0\n", "zero quaternion"),
                        ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "twice"), ("1 0 nan 0 0 0 0 1\n", "line 1")]:
        with pytest.raises(DataError) as e:
            read_tum_trajectory(write(tmp_path / "gt.txt", bad))
        assert needle in one_line(e, "gt.txt")


# --- association --------------------------------------------------------------------------

def associate_reference(a, b, max_difference):
    """TUM's associate.py, transcribed (offset 0)."""
    pairs = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) < max_difference)
    fa, fb, out = set(range(len(a))), set(range(len(b))), []
    for _, i, j in pairs:
        if i in fa and j in fb:
            fa.remove(i)
            fb.remove(j)
            out.append((i, j))
    return sorted(out)


def test_associate_matches_reference():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a = np.sort(rng.uniform(0, 3, 40))
        b = rng.uniform(0, 3, 30)  # unsorted on purpose
        ia, ib = associate(a, b, 0.05)
        assert list(zip(ia.tolist(), ib.tolist())) == associate_reference(a, b, 0.05)


def test_associate_one_to_one_and_drops_far():
    ia, ib = associate(np.array([0.0, 0.01, 1.0]), np.array([0.004, 0.5]), 0.02)
    assert ia.tolist() == [0] and ib.tolist() == [0]
    ia, ib = associate(np.array([]), np.array([1.0]), 0.02)
    assert len(ia) == len(ib) == 0


# --- interpolation ------------------------------------------------------------------------

def test_interpolate_midpoint_and_range():
    R1 = quat_to_rotmat(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))  # 90 deg about z
    poses = np.stack([np.eye(4), make_pose(R1, [2.0, 0, 0])])
    out = interpolate_poses(np.array([10.0, 11.0]), poses, np.array([10.5, 10.0, 11.0, 9.9, 11.1]))
    mid = out[0]
    np.testing.assert_allclose(mid[:3, 3], [1.0, 0, 0])
    assert rotation_angle_deg(mid[:3, :3]) == pytest.approx(45.0)
    np.testing.assert_allclose(mid[:3, :3] @ [1, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-12)
    np.testing.assert_allclose(out[1], poses[0], atol=1e-12)
    np.testing.assert_allclose(out[2], poses[1], atol=1e-12)
    assert np.isnan(out[3]).all() and np.isnan(out[4]).all()


def test_interpolate_gap_tolerance():
    poses = random_poses(2)
    out = interpolate_poses(np.array([0.0, 1.0]), poses, np.array([0.01, 0.5, 0.99]), max_gap=0.02)
    assert np.isfinite(out[0]).all() and np.isnan(out[1]).all() and np.isfinite(out[2]).all()


def test_interpolate_shorter_arc_and_single_sample():
    # the same rotation written with opposite quaternion signs must not swing through 360 deg
    Ra = quat_to_rotmat(np.array([0.0, 0.0, 0.0, 1.0]))
    Rb = quat_to_rotmat(-np.array([np.cos(1.6), 0, 0, np.sin(1.6)]))
    out = interpolate_poses(np.array([0.0, 1.0]), np.stack([make_pose(Ra, [0, 0, 0]), make_pose(Rb, [0, 0, 0])]), [0.5])
    assert rotation_angle_deg(Ra.T @ out[0, :3, :3]) < 5.0
    one = interpolate_poses(np.array([3.0]), random_poses(1), np.array([3.0, 3.1]))
    assert np.isfinite(one[0]).all() and np.isnan(one[1]).all()
