"""Loop closure inside the run, where it takes a process or real data: in real time the loop
closure runs in a process of its own and no frame waits for it (a correction still followed by the
map, tracker and trajectory); on real 7-Scenes frames a sequential run closes a right loop and
lowers the ATE."""

from __future__ import annotations

import csv
import os

import numpy as np
import pytest

from slamkit.formats.g2o import read_g2o
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry import make_pose, quat_to_rotmat
from slamkit.registry import default_registry
from slamkit.registry.compose import compose_run
from slamkit.run import checkpoint, pipeline

from support.data import SEVENSCENES, require_data
from support.loop_closing import loop_registry, offsets, run_shifted

pytestmark = pytest.mark.slow  # a process of the loop closure's own, or 260 real frames


@pytest.fixture
def registry():
    return loop_registry()


def test_in_real_time_the_run_follows_a_correction_without_waiting_for_it(tmp_path, registry, mode="realtime"):
    """The loop closure moves every keyframe 10 cm along x once: the whole trajectory is then
    10 cm along x of the truth, the frames before the correction (they followed their keyframe)
    and after it (tracked against the moved map, from the moved motion model) alike; keyframes.txt
    and the pose graph agree; the map is the uncorrected run's moved by 10 cm; loops.csv and
    pose_graph.g2o are written. In real time the loop closure sleeps 1.5 s a call in a process
    of its own, and no frame waits for it (each is tracked in less)."""
    log = tmp_path / "calls.txt"
    sleep = ["loop_closure.sleep_s=1.5", "mode=realtime", f"loop_closure.log={log}"] if mode == "realtime" else []
    metrics = run_shifted(registry, tmp_path / "shifted", *sleep)
    run_shifted(registry, tmp_path / "plain", "loop_closure=none", *(["mode=realtime"] if sleep else []))
    shifted = offsets(tmp_path / "shifted")
    assert np.abs(offsets(tmp_path / "plain")).max() < 0.01  # synthetic tracking: millimetres
    np.testing.assert_allclose(shifted, np.tile([0.10, 0.0, 0.0], (len(shifted), 1)), atol=0.01)
    assert metrics["loop_corrections"] == 1 and metrics["loops_accepted"] == 1
    _, keyframes = read_tum_trajectory(tmp_path / "shifted" / "keyframes.txt")
    graph = read_g2o(tmp_path / "shifted" / "pose_graph.g2o")
    np.testing.assert_allclose(graph.poses[:, :3, 3], keyframes[:len(graph.poses), :3, 3], atol=1e-6)
    with open(tmp_path / "shifted" / "loops.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["accepted"] == "True" and rows[0]["fitness"] == "0.9"
    shifted_map, _ = checkpoint.load_map(tmp_path / "shifted")
    plain_map, _ = checkpoint.load_map(tmp_path / "plain")
    shift = shifted_map.entry_means.mean(dim=0) - plain_map.entry_means.mean(dim=0)
    np.testing.assert_allclose(shift.numpy(), [0.10, 0.0, 0.0], atol=0.01)
    if mode == "realtime":
        pids = log.read_text().split()
        assert len(pids) >= 2 and str(os.getpid()) not in pids
        with open(tmp_path / "shifted" / "frames.csv") as f:
            tracking_ms = [float(r["tracking_ms"]) for r in csv.DictReader(f) if r["tracking_ms"]]
        assert len(tracking_ms) == 30 and max(tracking_ms) < 1000, max(tracking_ms)
        assert metrics["loop_closure_wall_s"] >= 1.5 * metrics["loop_closure_calls"] >= 3.0


def test_a_sequential_run_on_real_frames_closes_a_right_loop_and_lowers_the_ate(tmp_path):
    """7-Scenes redkitchen frames 300-559 (the camera comes back to the view of 300 at 524):
    tracking only, with loop_closure=pose_graph the run accepts loops that are all right by the
    issue's definition (5 cm, 3 degrees from the ground truth's relative pose) and ends with a
    lower ATE than without."""
    data = require_data(SEVENSCENES)
    registry = default_registry()
    base = ["dataset=sevenscenes", f"dataset.path={data}", "dataset.max_frames=260", "mapper=none", "progress=false",
            "eval.plot=false"]
    runs = {}
    for closure in ("none", "pose_graph"):
        cfg, names = compose_run([*base, f"loop_closure={closure}"], registry)
        runs[closure] = pipeline.run(cfg, registry, names, tmp_path / closure)
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
