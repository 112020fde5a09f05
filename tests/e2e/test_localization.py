"""`mode=localize` (issue 17): global registration of a real frame from an unknown pose, and
localising real sequences in a saved map (TUM fr1/rpy 100-149 in the map of 0-99, Replica
room0 10-19 in the map of 0-9), the map left as it was."""

from __future__ import annotations

import hashlib
import json
import signal
from pathlib import Path

import numpy as np
import pytest

from slamkit.formats.checkpoint import CHECKPOINT_NAME
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry.registration import GlobalRegistration
from slamkit.geometry.transforms import backproject, make_pose, so3_exp, transform_points
from slamkit.metrics.trajectory import ate
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import default_registry

from conftest import run_slamkit

pytest.importorskip("open3d")


def _frame(path: Path, index: int):
    cfg, names = compose_run(["dataset=tum", f"dataset.path={path}"])
    return default_registry().create("dataset", names["dataset"], cfg.dataset)[index]


def test_global_registration_finds_a_real_frame_moved_far_from_its_place(tum_path):
    frame = _frame(tum_path, 0)
    points, _ = backproject(frame.depth, frame.camera, 2)
    truth = make_pose(so3_exp(np.array([0.3, -1.2, 0.5])), np.array([1.5, -0.7, 2.0]))  # camera-to-"map"
    registration = GlobalRegistration(transform_points(truth, points), voxel=0.05)
    found = registration.register(points, seed=0)
    assert np.linalg.norm(found.pose[:3, 3] - truth[:3, 3]) < 0.02
    assert np.linalg.norm(found.pose[:3, :3] - truth[:3, :3]) < 0.03
    assert found.fitness > 0.9


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run(tmp_path: Path, out: Path, *args: str) -> dict:
    proc = run_slamkit(*args, "progress=false", "eval.plot=false", f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    return json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
def test_tum_frames_100_149_localise_in_the_map_of_frames_0_99(tmp_path, tum_path):
    """From an unknown start; ATE at most 1.5x the full run's on the same frames (tracking-only
    runs: the point is tracking in a fixed map)."""
    tum = ("dataset=tum", f"dataset.path={tum_path}", "mapper=none")
    _run(tmp_path, tmp_path / "map", *tum, "dataset.max_frames=100")
    _run(tmp_path, tmp_path / "full", *tum, "dataset.max_frames=150")
    before = _digest(tmp_path / "map" / CHECKPOINT_NAME)
    metrics = _run(tmp_path, tmp_path / "loc", *tum, "mode=localize", f"map={tmp_path / 'map'}",
                   "dataset.start=100", "dataset.max_frames=50")
    assert _digest(tmp_path / "map" / CHECKPOINT_NAME) == before  # the map is read, never written
    assert metrics["num_frames"] == 50 and metrics["localized_frames"] >= 48
    assert metrics["first_localized_index"] == 0
    _, est = read_tum_trajectory(tmp_path / "full" / "trajectory.txt")
    _, gt = read_tum_trajectory(tmp_path / "full" / "groundtruth.txt")
    full_on_those = ate(est[100:], gt[100:]).rmse_m
    assert metrics["ate_rmse_m"] <= 1.5 * full_on_those
    assert metrics["map_frame_rmse_m"] < 0.1  # in the map's own frame (it started at the ground-truth pose)


@pytest.mark.slow
def test_replica_frames_10_19_localise_in_the_map_of_frames_0_9(tmp_path, replica_path):
    replica = ("dataset=replica", f"dataset.path={replica_path}", "mapper=none")
    _run(tmp_path, tmp_path / "map", *replica, "dataset.max_frames=10")
    metrics = _run(tmp_path, tmp_path / "loc", *replica, "mode=localize", f"map={tmp_path / 'map'}",
                   "dataset.start=10")
    assert metrics["num_frames"] == 10 and metrics["localized_frames"] == 10
    assert metrics["map_frame_rmse_m"] < 0.02
    lines = (tmp_path / "loc" / "frames.csv").read_text().splitlines()
    assert lines[0].startswith("index,timestamp,localized,relocalized") and len(lines) == 11

    # a frame the tracker loses (no depth) is not localised; the next one is registered again
    from dataclasses import replace

    from slamkit.config import RunContext
    from slamkit.run.checkpoint import load_map
    from slamkit.run.localization import Localizer

    registry = default_registry()
    cfg, names = compose_run([*replica, "mode=localize", f"map={tmp_path / 'map'}", "dataset.start=10"])
    dataset = registry.create("dataset", names["dataset"], cfg.dataset)
    context = RunContext(tuning=dataset.tuning, build=registry.create)
    localizer = Localizer(cfg, registry.create("tracker", names["tracker"], cfg.tracker, context),
                          load_map(tmp_path / "map")[0])
    first, blind, after = dataset[0], dataset[1], dataset[2]
    steps = [localizer.step(first), localizer.step(replace(blind, depth=np.zeros_like(blind.depth))),
             localizer.step(after)]
    assert [(s.localized, s.relocalized) for s in steps] == [(True, True), (False, True), (True, True)]
    assert np.linalg.norm(steps[2].pose[:3, 3] - after.gt_pose[:3, 3]) < 0.01


@pytest.mark.slow
def test_an_interrupted_localisation_keeps_its_frames_and_exits_143_on_sigterm(tmp_path, tum_path):
    from test_run_lifecycle import Slamkit

    tum = ("dataset=tum", f"dataset.path={tum_path}", "mapper=none")
    _run(tmp_path, tmp_path / "map", *tum, "dataset.max_frames=5")
    out = tmp_path / "loc"
    run = Slamkit(*tum, "mode=localize", f"map={tmp_path / 'map'}", "dataset.max_frames=8", "progress=false",
                  f"hydra.run.dir={out}", cwd=tmp_path, pause_at="stream@3")
    run.wait_for("slamkit: paused at stream@3")
    run.send(signal.SIGTERM)
    code, stdout, stderr = run.finish()
    assert code == 128 + signal.SIGTERM and "Traceback" not in stderr, stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["status"], metrics["completed"], metrics["num_frames"]) == ("interrupted", False, 3)
    assert metrics["error"] == "interrupted (SIGTERM) during stream"
    assert "(incomplete: interrupted (SIGTERM) during stream)" in stdout
    timestamps, _ = read_tum_trajectory(out / "trajectory.txt")
    assert len(timestamps) == metrics["localized_frames"] > 0


def test_localize_needs_a_map(tmp_path):
    from slamkit.errors import ConfigError
    from slamkit.formats.checkpoint import CheckpointError
    from slamkit.run.checkpoint import load_map

    with pytest.raises(ConfigError, match="map: expected a run folder or checkpoint file with mode=localize"):
        compose_run(["mode=localize"])
    cfg, _ = compose_run(["mode=localize", "map=out/run", "growth.scale_c=3"])
    assert cfg.map == "out/run" and cfg.growth.scale_c == 3  # `map` names the saved map, `growth.` the map's growth
    with pytest.raises(CheckpointError, match=f"checkpoint {tmp_path / 'nothing'} not found"):
        load_map(tmp_path / "nothing")


def test_map_fit_tells_the_right_pose_from_a_shifted_one_by_shape_and_by_colour():
    """A textured wall 2 m ahead, as a map (a centre per pixel, with the pixel's colour) and as
    a frame: from the frame's own pose the map lies on its surface with its colours; 0.5 m
    closer it lies in front of it; 0.1 m to the side (the same wall, so the same depth) its
    colours no longer line up."""
    from slamkit.geometry.transforms import backproject, make_pose
    from slamkit.run.localization import map_fit
    from slamkit.types import Camera, Frame

    camera = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)
    depth = np.full((48, 64), 2.0, np.float32)
    frame = Frame(0, 0.0, texture, depth, camera, None)
    points, pixels = backproject(depth, camera)
    colors = texture.reshape(-1, 3)[pixels] / 255.0
    right = map_fit(frame, np.eye(4), points.astype(np.float64), colors)
    assert right.surface_agreement == 1.0 and right.color_correlation > 0.99
    closer = map_fit(frame, make_pose(np.eye(3), np.array([0.0, 0.0, 0.5])), points.astype(np.float64), colors)
    assert closer.surface_agreement == 0.0 and closer.color_correlation is None
    aside = map_fit(frame, make_pose(np.eye(3), np.array([0.1, 0.0, 0.0])), points.astype(np.float64), colors)
    assert aside.surface_agreement == 1.0 and abs(aside.color_correlation) < 0.3
