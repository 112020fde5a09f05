"""Sweeps through Hydra launchers, the report command, and reproducibility."""

from __future__ import annotations

import csv

import pytest

from slamkit.cli.report import main as report_main

from support.commands import run_slamkit

pytestmark = pytest.mark.slow  # every test here starts the slamkit command


def test_two_job_sweep_with_submitit_local_then_report(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_slamkit("-m", "tracker=gicp,kiss_icp", "keyframe=overlap", "dataset.num_frames=12",
                       "output.progress=false", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
                       f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert report_main([str(sweep)]) == 0
    with open(sweep / "report.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted(r["tracker"] for r in rows) == ["gicp", "kiss_icp"]
    assert all(float(r["ate_rmse_m"]) < 0.05 and r["n"] == "1" for r in rows)
    assert "| tracker |" in (sweep / "report.md").read_text()
    assert (sweep / "bar_ate_rmse_m.png").stat().st_size > 0 and (sweep / "trajectories.png").exists()


def test_seed_sweep_rows_average_with_spread(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_slamkit("+experiment=ablation_regularization", "dataset.num_frames=8", "seed=0,1",
                       "output.progress=false", "iterations_per_frame=1", "mapper.resolution_scale=0.25",
                       "mapper.eval_every=8", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert report_main([str(sweep)]) == 0
    rows = list(csv.DictReader(open(sweep / "report.csv")))
    assert [r["tracker.regularization"] for r in rows] == ["none", "plane", "ellipse"]
    assert all(r["n"] == "2" for r in rows)


def test_report_on_an_empty_folder_is_a_clear_error(tmp_path, capsys):
    assert report_main([str(tmp_path)]) == 2
    assert "no runs (metrics.json) found" in capsys.readouterr().err


def test_sequential_runs_are_bit_identical_for_the_same_seed(tmp_path):
    outputs = []
    for name in ("a", "b"):
        out = tmp_path / name
        proc = run_slamkit("tracker=gicp", "keyframe=overlap", "mapper=gaussian_splatting", "mapper/sampler=random",
                           "iterations_per_frame=2", "final_iterations=0", "mapper.eval_every=4",
                           "dataset.num_frames=12", "seed=3", "output.progress=false", f"hydra.run.dir={out}",
                           cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        outputs.append(((out / "trajectory.txt").read_bytes(), (out / "map.ply").read_bytes()))
    assert outputs[0] == outputs[1]  # trajectory and optimised map, bit for bit
