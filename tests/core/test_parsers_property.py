"""Property-based tests of the file parsers (TUM lists and trajectories, Replica and 7-Scenes
files, 3DGS PLY headers, folder-dataset intrinsics files): any input gives either a valid result
or slamkit's own one-line DataError naming the file (never another exception). Part of the
fault suite of issue 19 (tests/e2e/test_faults.py); each test tries SETTINGS.max_examples inputs."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slamkit.errors import DataError
from slamkit.formats.ply import PROPERTIES, load_ply
from slamkit.formats.tum import associate, read_float_table, read_tum_list, read_tum_trajectory
from slamkit_plugins.datasets.folder import INTRINSICS_KEYS
from slamkit_plugins.datasets.folder import read_intrinsics as read_folder_intrinsics
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


def _check(parser, text: str | bytes, validate, name: str = "input.txt") -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
        try:
            result = parser(path)
        except DataError as exc:
            message = str(exc)
            assert "\n" not in message and name in message, message
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
@given(st.one_of(TEXT, st.dictionaries(st.sampled_from(["camera", "w", "h", "fx", "fy", "cx", "cy", "scale"]),
                                        st.one_of(st.integers(-5, 2000), st.floats(), st.text(max_size=5),
                                                  st.sampled_from([600, 599.5, 1200, 680])), min_size=5)
                 .map(lambda d: __import__("json").dumps({"camera": d}))))
def test_replica_cam_params_parser(text):
    def valid(result):
        camera, scale = result
        assert camera.implausible() == [], camera
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


# --- 3DGS PLY files: a header from PLY's grammar with wrong words mixed in, and a body --------------

PLY_TYPES = st.sampled_from(["float", "double", "uchar", "int", "uint16", "float32", "half", "list uchar int", ""])
PLY_NAMES = st.sampled_from([*PROPERTIES, "f_rest_0", "x", "", "vertex"])
PLY_COUNT = st.one_of(st.integers(0, 4).map(str), st.sampled_from(["-1", "abc", "99999999999", "1.5", "\u00b2"]))
PLY_ELEMENT = st.tuples(st.sampled_from(["vertex", "face", "vertex"]), PLY_COUNT,
                        st.lists(st.tuples(PLY_TYPES, PLY_NAMES), max_size=20))
PLY_FORMAT = st.sampled_from(["ascii 1.0", "binary_little_endian 1.0", "binary_big_endian 1.0", "binary 1.0", ""])


def _ply_header(magic: str, fmt: str | None, elements, comment: str, end: str) -> str:
    lines = [magic] + ([f"format {fmt}"] if fmt is not None else []) + [f"comment {comment}"]
    for name, count, props in elements:
        lines.append(f"element {name} {count}")
        lines += [f"property {t} {n}" for t, n in props]
    return "\n".join(lines + [end]) + "\n"


PLY = st.builds(
    lambda header, body: header.encode("utf-8", "surrogatepass") + body,
    st.builds(_ply_header, st.sampled_from(["ply", "ply", "PLY", "ply\r"]), st.one_of(st.none(), PLY_FORMAT),
              st.lists(PLY_ELEMENT, max_size=3), st.text(max_size=10).filter(lambda t: "\n" not in t and "\r" not in t),
              st.sampled_from(["end_header", "end_header", "", "end_head"])),
    st.one_of(st.binary(max_size=400), LINE.map(lambda line: (line + "\n").encode()),
              st.lists(LINE, max_size=6).map(lambda lines: "\n".join(lines).encode())),
)


@SETTINGS
@given(st.one_of(PLY, st.binary(max_size=200)))
def test_ply_reader(data):
    def valid(gaussian_map):
        assert len(gaussian_map) >= 0 and gaussian_map.means.shape == (len(gaussian_map), 3)

    _check(load_ply, data, valid, name="map.ply")


# --- folder-dataset intrinsics files (YAML or JSON): keys with any values -----------------------

INTRINSIC_VALUE = st.one_of(
    st.floats(), st.integers(-10**3, 10**3), st.integers(-10**400, 10**400), st.booleans(), st.none(),
    st.text(max_size=5), st.lists(st.integers(), max_size=2), st.sampled_from([640, 480, 517.3, 318.6, 5000]),
)
INTRINSICS_MAP = st.dictionaries(st.sampled_from([*INTRINSICS_KEYS, "depth_trunc", "other"]), INTRINSIC_VALUE,
                                 max_size=9)


def _valid_intrinsics(result):
    camera, depth_scale, depth_trunc = result
    assert camera.implausible() == [], camera
    assert np.isfinite(depth_scale) and depth_scale > 0
    assert depth_trunc is None or (np.isfinite(depth_trunc) and depth_trunc > 0)


@SETTINGS
@given(st.one_of(INTRINSICS_MAP.map(lambda d: __import__("yaml").safe_dump(d)), TEXT))
def test_folder_intrinsics_yaml_parser(text):
    _check(read_folder_intrinsics, text, _valid_intrinsics, name="intrinsics.yaml")


@SETTINGS
@given(st.one_of(INTRINSICS_MAP.map(lambda d: __import__("json").dumps(d)), TEXT))
def test_folder_intrinsics_json_parser(text):
    _check(read_folder_intrinsics, text, _valid_intrinsics, name="intrinsics.json")
