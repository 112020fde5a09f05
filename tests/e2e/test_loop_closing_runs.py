"""Loop closure inside the run, where it takes a process or real data: in real time the loop
closure runs in a process of its own and no frame waits for it (a correction still followed by the
map, tracker and trajectory); on real 7-Scenes frames a sequential run closes a right loop and
lowers the ATE."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry import make_pose, quat_to_rotmat
from slamkit.registry import default_registry
from slamkit.registry.compose import compose_run
from slamkit.run import pipeline

from support.data import SEVENSCENES, require_data
from support.loop_closing import check_run_follows_shift, loop_registry

pytestmark = pytest.mark.slow  # a process of the loop closure's own, or 260 real frames


@pytest.fixture
def registry():
    return loop_registry()


def test_in_real_time_the_run_follows_a_correction_without_waiting_for_it(tmp_path, registry):
    """As in sequential mode (tests/core/test_loop_closing.py), with the loop closure sleeping
    1.5 s a call in a process of its own: no frame waits for it."""
    check_run_follows_shift(tmp_path, registry, "realtime")


def test_a_sequential_run_on_real_frames_closes_a_right_loop_lowers_the_ate_and_repeats_to_the_byte(tmp_path):
    """7-Scenes redkitchen frames 300-559 (the camera comes back to the view of 300 at 524):
    tracking only, with loop_closure=pose_graph the run accepts loops that are all right by the
    issue's definition (5 cm, 3 degrees from the ground truth's relative pose; loops.csv's
    gt_error columns say the same) and ends with a lower ATE than without; run again, it writes
    the same trajectory.txt and loops.csv, byte for byte (registration is deterministic)."""
    data = require_data(SEVENSCENES)
    registry = default_registry()
    base = ["dataset=sevenscenes", f"dataset.path={data}", "dataset.max_frames=260", "mapper=none",
            "output.progress=false",
            "output.plot=false"]
    runs = {}
    for name, closure in (("none", "none"), ("pose_graph", "pose_graph"), ("again", "pose_graph")):
        cfg, names = compose_run([*base, f"loop_closure={closure}"], registry)
        runs[name] = pipeline.run(cfg, registry, names, tmp_path / name)
    for file in ("trajectory.txt", "loops.csv", "pose_graph.g2o"):
        assert (tmp_path / "pose_graph" / file).read_bytes() == (tmp_path / "again" / file).read_bytes(), file
    assert runs["pose_graph"]["loops_accepted"] >= 1
    assert runs["pose_graph"]["ate_rmse_m"] < runs["none"]["ate_rmse_m"]
    _, gt = read_tum_trajectory(tmp_path / "pose_graph" / "groundtruth.txt")
    from slamkit.geometry import nearest_rotation
    from slamkit.geometry.pose_graph import pose_difference, relative_pose

    gt[:, :3, :3] = nearest_rotation(gt[:, :3, :3])
    with open(tmp_path / "pose_graph" / "loops.csv") as f:
        accepted = [r for r in csv.DictReader(f) if r["accepted"] == "True"]
    for r in accepted:
        q = np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")])
        found = make_pose(quat_to_rotmat(q), [float(r[k]) for k in ("tx", "ty", "tz")])
        error_m, error_deg = pose_difference(found, relative_pose(gt[int(r["match_frame"])], gt[int(r["frame"])]))
        assert error_m <= 0.05 and error_deg <= 3.0, r
        assert np.isclose(float(r["gt_error_m"]), error_m, atol=1e-6), r
        # groundtruth.txt's quaternions come from the files' non-orthonormal matrices: ~1e-3 deg apart
        assert np.isclose(float(r["gt_error_deg"]), error_deg, atol=0.01), r
