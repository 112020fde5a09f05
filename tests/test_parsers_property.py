"""Property-based tests of the dataset file parsers: any input gives either a valid result or
slamkit's own one-line DataError naming the file (never another exception)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slamkit.errors import DataError
from slamkit.formats.tum import associate, read_float_table, read_tum_list, read_tum_trajectory
from slamkit_plugins.datasets.replica import read_cam_params
from slamkit_plugins.datasets.sevenscenes import read_intrinsics, read_pose_file

NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.sampled_from(["nan", "inf", "-0", "1e400", "0x10", "", "abc", "1,5", "1.5.2", "#", "\t"]),
)
LINE = st.lists(NUMBER, min_size=0, max_size=18).map(" ".join)
TEXT = st.one_of(st.lists(LINE, max_size=12).map("\n".join), st.text(max_size=300),
                 st.binary(max_size=200))
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _check(parser, text: str | bytes, validate) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "input.txt"
        path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
        try:
            result = parser(path)
        except DataError as exc:
            message = str(exc)
            assert "\n" not in message and "input.txt" in message, message
            return
        validate(result)


def _valid_trajectory(result):
    ts, poses = result
    assert len(ts) == len(poses) and np.all(np.isfinite(ts)) and np.all(np.diff(ts) > 0)
    assert np.all(np.isfinite(poses))
    R = poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-6)


@SETTINGS
@given(TEXT)
def test_tum_trajectory_parser(text):
    _check(read_tum_trajectory, text, _valid_trajectory)


@SETTINGS
@given(st.lists(st.tuples(NUMBER, st.sampled_from(["rgb/a.png", "d/1.png", "", "x y"])), max_size=10)
       .map(lambda rows: "\n".join(f"{t} {f}" for t, f in rows)))
def test_tum_list_parser(text):
    def valid(result):
        ts, names = result
        assert len(ts) == len(names) and np.all(np.isfinite(ts)) and np.all(np.diff(ts) > 0)
        assert all(isinstance(n, str) and n for n in names)

    _check(read_tum_list, text, valid)


@SETTINGS
@given(TEXT)
def test_replica_trajectory_table_parser(text):
    def valid(table):
        assert table.ndim == 2 and table.shape[1] == 16 and np.all(np.isfinite(table))

    _check(lambda p: read_float_table(p, 16, "16 floats per line (a 4x4 pose)"), text, valid)


@SETTINGS
@given(TEXT)
def test_sevenscenes_pose_and_intrinsics_parsers(text):
    def valid_pose(T):
        assert T.shape == (4, 4) and np.all(np.isfinite(T))

    def valid_intrinsics(k):
        assert len(k) == 4 and all(np.isfinite(v) for v in k) and k[0] > 0 and k[1] > 0

    _check(read_pose_file, text, valid_pose)
    _check(read_intrinsics, text, valid_intrinsics)


@SETTINGS
@given(st.one_of(TEXT, st.dictionaries(st.sampled_from(["camera", "w", "h", "fx", "scale"]),
                                        st.one_of(st.integers(-5, 2000), st.floats(), st.text(max_size=5)))
                 .map(lambda d: __import__("json").dumps({"camera": d}))))
def test_replica_cam_params_parser(text):
    def valid(result):
        camera, scale = result
        assert camera.width > 0 and camera.height > 0 and camera.fx > 0 and camera.fy > 0
        assert scale is None or (np.isfinite(scale) and scale > 0)

    _check(read_cam_params, text, valid)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0, 100, allow_nan=False), max_size=30, unique=True),
       st.lists(st.floats(0, 100, allow_nan=False), max_size=30, unique=True),
       st.floats(0, 1))
def test_association_is_one_to_one_within_tolerance(a, b, tol):
    a, b = np.sort(np.array(a)), np.sort(np.array(b))
    ia, ib = associate(a, b, tol)
    assert len(set(ia.tolist())) == len(ia) and len(set(ib.tolist())) == len(ib)
    assert np.all(np.abs(a[ia] - b[ib]) < tol + 1e-12)
