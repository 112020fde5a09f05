"""`slamkit dataset=rosbag`: a bag of the real TUM frames gives the TUM folder run's poses, and
bad bags exit with status 2 and one line. The dataset itself: tests/plugins/test_rosbag.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slamkit.formats.tum import read_tum_trajectory

from support.commands import run_slamkit
from support.rosbag_writer import write_tum_bag

rosbags = pytest.importorskip("rosbags", reason="rosbags is the optional extra `rosbag` (in `test`)")


@pytest.mark.slow
def test_rosbag_run_gives_the_tum_folder_run_poses(tmp_path, tum_path):
    """The same G-ICP run on the folder and on a ROS1 bag of its frames: identical poses and ATE."""
    n = 20
    bag = write_tum_bag(tum_path, tmp_path / "fr1.bag", n)
    common = ["mapper=none", "output.progress=false", "output.plot=false", "dataset.depth_trunc=3.0",
              "dataset.prefetch=2"]
    runs = {}
    for name, args in {
        "folder": ["dataset=tum", f"dataset.path={tum_path}", f"dataset.max_frames={n}"],
        "bag": ["dataset=rosbag", f"dataset.path={bag}", "dataset.depth_scale=5000",
                f"dataset.groundtruth={tum_path / 'groundtruth.txt'}"],
    }.items():
        out = tmp_path / name
        proc = run_slamkit(*args, *common, f"hydra.run.dir={out}", cwd=tmp_path, env_extra={"OMP_NUM_THREADS": "1"})
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs[name] = (read_tum_trajectory(out / "trajectory.txt"), json.loads((out / "metrics.json").read_text()))
    (t_folder, poses_folder), m_folder = runs["folder"]
    (t_bag, poses_bag), m_bag = runs["bag"]
    assert len(t_bag) == len(t_folder) == m_bag["num_frames"] > 15
    np.testing.assert_allclose(t_bag, t_folder, atol=1e-6)
    np.testing.assert_allclose(poses_bag, poses_folder, atol=1e-6)
    assert m_bag["ate_rmse_m"] == pytest.approx(m_folder["ate_rmse_m"], abs=1e-6)
    assert m_bag["ate_rmse_m"] < 0.05


@pytest.mark.slow
@pytest.mark.parametrize("how, message", [
    ("no_images", "has no image topic"),
    ("truncated", "cannot read ROS bag"),
    ("sizes", "depth images are 320x240 but the colour images are 640x480"),
])
def test_bad_bags_exit_2_with_one_line(tmp_path, tum_path, how, message):
    path = tmp_path / "x.bag"
    if how == "truncated":
        data = write_tum_bag(tum_path, path, 2).read_bytes()
        path.write_bytes(data[: len(data) // 2])
    else:
        write_tum_bag(tum_path, path, 2, image_topics=how != "no_images",
                      depth_size=(320, 240) if how == "sizes" else None)
    proc = run_slamkit("dataset=rosbag", f"dataset.path={path}", "mapper=none", "output.progress=false",
                       f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("slamkit: error: ") and message in lines[0], proc.stderr
    assert str(path) in lines[0]
