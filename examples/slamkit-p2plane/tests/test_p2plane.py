"""Tests of the p2plane tracker: the solver on a synthetic cloud, the config, the plugin's
registration, and a real run of the `slamkit` command on TUM fr1/rpy."""

from __future__ import annotations

import json
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest

from slamkit.config import RunContext
from slamkit.downloads.excerpts import find_test_data
from slamkit.errors import ConfigError
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry.transforms import invert_pose, make_pose, rotation_angle_deg, so3_exp, transform_points
from slamkit.registry.discovery import discover
from slamkit.tuning import DatasetTuning
from slamkit_p2plane import Model, P2PlaneConfig, P2PlaneTracker, point_to_plane

# The real test data: $SLAMKIT_DATA, else the shared folder beside the slamkit checkout, else where
# `slamkit-data download test-data` puts it.
DATA = find_test_data(Path(__file__).resolve().parents[3])
TUM = DATA / "tum_fr1_rpy_first150"


def room_corner(rng: np.random.Generator, n: int) -> np.ndarray:
    """n points on a floor and two walls (1.5 m squares): planes that constrain all 6 DoF."""
    u, v = rng.uniform(0, 1.5, (2, n))
    plane = rng.integers(0, 3, n)
    zero = np.zeros(n)
    return np.where(plane[:, None] == 0, np.stack([u, v, zero], 1),
                    np.where(plane[:, None] == 1, np.stack([u, zero, v], 1), np.stack([zero, u, v], 1)))


def test_recovers_a_known_transform_on_a_synthetic_cloud():
    rng = np.random.default_rng(0)
    model = Model(room_corner(rng, 30_000), knn=10)
    true_pose = make_pose(so3_exp(np.radians([2.0, -3.0, 1.5])), [0.03, -0.02, 0.025])
    # Another sampling of the same surfaces, seen from the camera at true_pose.
    camera_points = transform_points(invert_pose(true_pose), room_corner(rng, 5_000))
    pose, matched, _ = point_to_plane(model, camera_points, np.eye(4), max_distance=0.1, huber=0.005,
                                      max_iterations=30, tolerance=1e-8)
    error = invert_pose(true_pose) @ pose
    assert np.linalg.norm(error[:3, 3]) < 1e-3
    assert rotation_angle_deg(error[:3, :3]) < 0.05
    assert matched > 4_500


def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="tracker.voxel_size"):
        P2PlaneConfig(voxel_size=0)
    with pytest.raises(ConfigError, match="tracker.knn"):
        P2PlaneConfig(knn=2)
    tracker = P2PlaneTracker(P2PlaneConfig().resolve(RunContext()))  # nulls: the dataset's tuning
    assert tracker.pixel_stride == DatasetTuning().tracking_pixel_stride


def test_registered_through_the_entry_point():
    assert any(e.name == "p2plane" and e.value == "slamkit_p2plane" for e in entry_points(group="slamkit"))
    spec = discover().get("tracker", "p2plane")
    assert spec.cls is P2PlaneTracker and spec.config is P2PlaneConfig


@pytest.mark.slow
def test_slamkit_runs_p2plane_on_tum(tmp_path):
    if not TUM.is_dir():
        pytest.skip(f"shared data not found at {TUM} (`slamkit-data download test-data` fetches it, or set "
                    f"SLAMKIT_DATA)")
    out = tmp_path / "run"
    slamkit = Path(sys.executable).with_name("slamkit")
    proc = subprocess.run(
        [str(slamkit), "tracker=p2plane", "dataset=tum", f"dataset.path={TUM}", "dataset.max_frames=30",
         "mapper=none", "output.progress=false", f"hydra.run.dir={out}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    timestamps, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(timestamps) == 30 and np.isfinite(poses).all()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["lost_frames"] == 0
    assert metrics["ate_rmse_m"] < 0.10
