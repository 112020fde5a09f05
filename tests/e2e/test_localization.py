"""`mode=localize` (issue 17): localising real sequences in a saved map (TUM fr1/rpy 100-149 in
the map of 0-99, Replica room0 10-19 in the map of 0-9), the map left as it was. Global
registration and the map fit on their own: tests/core/test_localization_parts.py."""

from __future__ import annotations

import hashlib
import json
import signal
from pathlib import Path

import numpy as np
import pytest

from slamkit.formats.checkpoint import CHECKPOINT_NAME
from slamkit.formats.tum import read_tum_trajectory
from slamkit.metrics.trajectory import ate
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import default_registry

from support.commands import run_slamkit

pytest.importorskip("open3d")


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run(tmp_path: Path, out: Path, *args: str) -> dict:
    proc = run_slamkit(*args, "output.progress=false", "output.plot=false", f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    return json.loads((out / "metrics.json").read_text())


@pytest.mark.slow
def test_tum_frames_100_149_localise_in_the_map_of_frames_0_99(tmp_path, tum_path):
    """From an unknown start; ATE at most 1.5x the full run's on the same frames (tracking-only
    runs: the point is tracking in a fixed map)."""
    tum = ("dataset=tum", f"dataset.path={tum_path}", "mapper=none")
    _run(tmp_path, tmp_path / "map", *tum, "dataset.max_frames=100", "checkpoint.save=true")
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
    _run(tmp_path, tmp_path / "map", *replica, "dataset.max_frames=10", "checkpoint.save=true")
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
    from support.commands import Slamkit

    tum = ("dataset=tum", f"dataset.path={tum_path}", "mapper=none")
    _run(tmp_path, tmp_path / "map", *tum, "dataset.max_frames=5", "checkpoint.save=true")
    out = tmp_path / "loc"
    run = Slamkit(*tum, "mode=localize", f"map={tmp_path / 'map'}", "dataset.max_frames=8", "output.progress=false",
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
