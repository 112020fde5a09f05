"""Third-party plugins from the command line: a plugin installed as a distribution runs with its
config, its config's validation and an unknown name are one line, and a plugin that raises stops
the run cleanly, naming it. Discovery itself: tests/core/test_registry.py."""

from __future__ import annotations

import json

import pytest

from support.commands import run_slamkit


@pytest.mark.slow
def test_third_party_plugin_runs_from_the_cli_with_its_config(plugin_dir, tmp_path):
    out = tmp_path / "run"
    env = {"PYTHONPATH": str(plugin_dir)}
    proc = run_slamkit("tracker=still", "tracker.offset=0.5", "dataset.num_frames=8", "output.progress=false",
                       f"hydra.run.dir={out}", cwd=tmp_path, env_extra=env)
    assert proc.returncode == 0, proc.stderr
    lines = (out / "trajectory.txt").read_text().splitlines()
    assert len(lines) == 8
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == 8 and metrics["ate_rmse_m"] > 0


@pytest.mark.slow
def test_third_party_config_validation_and_unknown_name_from_the_cli(plugin_dir, tmp_path):
    env = {"PYTHONPATH": str(plugin_dir)}
    bad = run_slamkit("tracker=still", "tracker.offset=-1", f"hydra.run.dir={tmp_path / 'x'}", cwd=tmp_path,
                      env_extra=env)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines()[-1] == "slamkit: error: tracker.offset: expected >= 0, got -1.0"
    assert "Traceback" not in bad.stderr
    unknown = run_slamkit("tracker=nope", cwd=tmp_path, env_extra=env)
    assert unknown.returncode == 2
    assert "unknown tracker 'nope'; available:" in unknown.stderr and "still" in unknown.stderr


@pytest.mark.slow
def test_a_plugin_that_raises_stops_the_run_cleanly_naming_it(plugin_dir, tmp_path):
    out = tmp_path / "run"
    proc = run_slamkit("tracker=still", "tracker.fail_at=3", "dataset.num_frames=8", f"hydra.run.dir={out}",
                       cwd=tmp_path, env_extra={"PYTHONPATH": str(plugin_dir)})
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        "slamkit: error: tracker plugin 'still' failed in track(): ValueError: simulated failure")
    assert len((out / "trajectory.txt").read_text().splitlines()) == 3
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["completed"] is False and "simulated failure" in metrics["error"]
    assert "Traceback" in (out / "slamkit.log").read_text()  # the log keeps the details
