"""The `slamkit` command end to end: run outputs (the DESIGN.md contract) and user errors."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from slamkit.formats.tum import read_tum_trajectory

from support.commands import run_slamkit
from support.config_reference import BAD
from support.folders import tiny_tum

pytestmark = pytest.mark.slow  # every test here starts the slamkit command

CONTRACT_KEYS = {"num_frames", "num_keyframes", "fps", "tracking_fps", "tracking_time_s", "mapping_time_s",
                 "lost_frames", "completed", "ate_rmse_m", "ate_mean_m"}


def _ok(proc):
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc


def _one_line_error(proc, *needles):
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("slamkit: error: ")
    for needle in needles:
        assert needle in last, last
    return last


def test_default_run_on_synthetic_prints_ate_and_fps(tmp_path):
    out = tmp_path / "run"
    proc = _ok(run_slamkit("dataset.num_frames=20", f"hydra.run.dir={out}", cwd=tmp_path))
    assert "ATE RMSE" in proc.stdout and "frames/s" in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert CONTRACT_KEYS <= set(metrics)
    assert metrics["completed"] is True and metrics["num_frames"] == 20
    assert metrics["ate_rmse_m"] < 0.05
    for name in ("trajectory.txt", "frames.csv", "trajectory.png", ".hydra/config.yaml", "slamkit.log"):
        assert (out / name).is_file(), name
    assert "synthetic: 20 frames" in (out / "slamkit.log").read_text()
    rows = list(csv.DictReader(open(out / "frames.csv")))
    assert len(rows) == 20 and rows[0]["tracking_iterations"] == "0"  # the first frame: no map to align to
    assert all(int(r["tracking_iterations"]) >= 1 for r in rows[1:])
    assert {r["fallback"] for r in rows} <= {"", "previous pose", "coarse to fine", "global registration"}


@pytest.mark.parametrize("dataset,fixture,frames", [("tum", "tum_path", 40), ("replica", "replica_path", 20)])
def test_kiss_icp_on_real_data_writes_poses_and_finite_ate(dataset, fixture, frames, request, tmp_path):
    path = request.getfixturevalue(fixture)
    out = tmp_path / "run"
    _ok(run_slamkit(f"dataset={dataset}", f"dataset.path={path}", f"dataset.max_frames={frames}",
                    "tracker=kiss_icp", "mapper=none", f"hydra.run.dir={out}", cwd=tmp_path))
    timestamps, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(timestamps) == frames and np.all(np.isfinite(poses))
    metrics = json.loads((out / "metrics.json").read_text())
    assert np.isfinite(metrics["ate_rmse_m"]) and metrics["ate_rmse_m"] < 0.1
    assert metrics["ate_mean_m"] <= metrics["ate_rmse_m"]


def test_sequence_without_ground_truth_runs_with_null_ate(tum_path, tmp_path):
    seq = tiny_tum(tmp_path / "rgbd_dataset_freiburg1_x", frames=12)
    (seq / "groundtruth.txt").unlink()
    out = tmp_path / "run"
    proc = _ok(run_slamkit("dataset=tum", f"dataset.path={seq}", f"hydra.run.dir={out}", cwd=tmp_path))
    assert "n/a (no ground truth)" in proc.stdout
    assert len(read_tum_trajectory(out / "trajectory.txt")[0]) == 12
    assert json.loads((out / "metrics.json").read_text())["ate_rmse_m"] is None


def test_bad_input_gives_one_line_errors(tum_path, tmp_path):
    missing = tmp_path / "nope"
    _one_line_error(run_slamkit("dataset=tum", f"dataset.path={missing}", cwd=tmp_path), str(missing))
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(run_slamkit("dataset=replica", f"dataset.path={empty}", cwd=tmp_path), str(empty))
    seq = tiny_tum(tmp_path / "corrupt", frames=12)
    victim = sorted((seq / "depth").iterdir())[5]
    victim.write_bytes(victim.read_bytes()[:200])
    _one_line_error(run_slamkit("dataset=tum", f"dataset.path={seq}", f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path),
                    victim.name)
    # the frames before the corrupt one are kept
    assert len(read_tum_trajectory(tmp_path / "r" / "trajectory.txt")[0]) == 5
    _one_line_error(run_slamkit("dataset=tum", f"dataset.path={tum_path}", "dataset.gt_path=missing_gt.txt",
                                cwd=tmp_path), "missing_gt.txt")


def test_config_errors_fail_in_one_line_before_work(tmp_path):
    _one_line_error(run_slamkit("dataset.stride=0", cwd=tmp_path), "dataset.stride", "got 0")
    _one_line_error(run_slamkit("dataset.max_frames=abc", cwd=tmp_path), "dataset.max_frames", "abc")
    _one_line_error(run_slamkit("tracker.no_such_key=1", cwd=tmp_path), "no_such_key")
    _one_line_error(run_slamkit("mode=fast", cwd=tmp_path), "mode")
    assert not (tmp_path / "outputs").exists()  # nothing ran


def test_the_mappers_parts_are_chosen_under_it_and_an_old_spelling_is_one_line(tmp_path):
    """`mapper/rasterizer=torch` chooses the mapper's rasteriser and `mapper.rasterizer.FIELD` sets
    its options; a wrong name fails in one line listing the others, and 0.2's spelling
    (`rasterizer=torch`) in one line naming the new one."""
    out = tmp_path / "run"
    _ok(run_slamkit("dataset.num_frames=4", "mapper=gaussian_splatting", "mapper/rasterizer=torch",
                    "mapper.rasterizer.max_pairs_per_chunk=4096", "final_iterations=2", f"hydra.run.dir={out}",
                    cwd=tmp_path))
    config = (out / ".hydra" / "config.yaml").read_text()
    assert "max_pairs_per_chunk: 4096" in config
    _one_line_error(run_slamkit("mapper=gaussian_splatting", "mapper/rasterizer=nope", cwd=tmp_path),
                    "unknown rasterizer 'nope'", "cpu")
    _one_line_error(run_slamkit("mapper=gaussian_splatting", "rasterizer=torch", cwd=tmp_path),
                    "write mapper/rasterizer=torch")


def test_on_error_skip_marks_an_unreadable_frame_lost_and_goes_on(tum_path, tmp_path):
    seq = tiny_tum(tmp_path / "rgbd_dataset_freiburg1_y", frames=12)
    victim = sorted((seq / "rgb").iterdir())[4]
    victim.write_bytes(b"not a png")
    out = tmp_path / "run"
    proc = _ok(run_slamkit("dataset=tum", f"dataset.path={seq}", "dataset.on_error=skip", f"hydra.run.dir={out}",
                           cwd=tmp_path))
    assert "1 lost" in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["lost_frames"] == 1 and metrics["completed"] is True
    timestamps, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(timestamps) == 12 and np.allclose(poses[4], poses[3])
    assert "unreadable" in (out / "frames.csv").read_text() and victim.name in (out / "slamkit.log").read_text()


def test_the_command_exits_2_with_one_line_for_each(tmp_path):
    for select, bad, named in BAD[::3]:
        proc = run_slamkit("mapper=gaussian_splatting", select, bad, f"hydra.run.dir={tmp_path / 'x'}", cwd=tmp_path)
        assert proc.returncode == 2, (bad, proc.stderr[-500:])
        last = proc.stderr.strip().splitlines()[-1]
        assert last.startswith("slamkit: error: ") and named in last and "Traceback" not in proc.stderr


def test_hydras_own_options_behave_as_in_any_hydra_app(tmp_path):
    """--cfg job prints the composed config (the run's settings in their groups), --info what Hydra
    knows, --help the app's help; no run."""
    job = _ok(run_slamkit("--cfg", "job", "tracker=kiss_icp", "realtime.fps_limit=30", cwd=tmp_path))
    assert "\ntracker:" in job.stdout and "\nmode: sequential" in job.stdout
    assert "\nrealtime:\n  fps_limit: 30" in job.stdout and "\noutput:\n  existing_outputs: refuse" in job.stdout
    info = _ok(run_slamkit("--info", "config", cwd=tmp_path))
    assert "Config search path" in info.stdout
    helped = _ok(run_slamkit("--help", cwd=tmp_path))
    assert "Powered by Hydra" in helped.stdout
    assert not (tmp_path / "outputs").exists()


#: The slamkit command in a fresh process, every composition of the configuration counted (Hydra
#: composes through `ConfigLoaderImpl.load_configuration`, whoever asks: the command, a check, Hydra).
COUNTING = """
import sys
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from slamkit.cli.main import Command

calls = []
load = ConfigLoaderImpl.load_configuration
def counted(self, config_name, overrides, *args, **kwargs):
    calls.append(" ".join(overrides))
    return load(self, config_name, overrides, *args, **kwargs)
ConfigLoaderImpl.load_configuration = counted
try:
    Command().main(sys.argv[1:])
finally:
    for call in calls:
        print(f"composed: {call}", file=sys.stderr)
    print(f"compositions: {len(calls)}", file=sys.stderr)
"""


def _counted(*args, cwd):
    """The slamkit command run with `args`, every composition counted (`COUNTING`)."""
    import subprocess
    import sys

    return _ok(subprocess.run([sys.executable, "-c", COUNTING, *args], cwd=cwd, capture_output=True, text=True,
                              timeout=600))


def test_a_run_and_its_resume_compose_the_configuration_once(tmp_path):
    run_dir = tmp_path / "run"
    first = _counted("dataset.num_frames=12", "dataset.max_frames=6", "output.progress=false", "output.plot=false",
                     "checkpoint.save=true", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert first.stderr.strip().splitlines()[-1] == "compositions: 1", first.stderr
    assert (run_dir / ".hydra" / "config.yaml").is_file() and (run_dir / "metrics.json").is_file()
    resumed = _counted(f"resume={run_dir}", "dataset.max_frames=12", cwd=tmp_path)
    assert resumed.stderr.strip().splitlines()[-1] == "compositions: 1", resumed.stderr
    assert json.loads((run_dir / "metrics.json").read_text())["num_frames"] == 12


def test_a_sweep_composes_each_job_once(tmp_path):
    """`-m` with two values: the sweep's configuration composed once and each job's once (checked
    before the first job starts, then run from that composition), not again by Hydra's sweeper
    and launcher; both jobs run."""
    sweep_dir = tmp_path / "sweep"
    proc = _counted("-m", "dataset.num_frames=6", "dataset.max_frames=3,4", "output.progress=false",
                    "output.plot=false",
                    "checkpoint.save=false", f"hydra.sweep.dir={sweep_dir}", cwd=tmp_path)
    composed = [line for line in proc.stderr.splitlines() if line.startswith("composed: ")]
    for value in ("dataset.max_frames=3", "dataset.max_frames=4"):
        assert sum(value in line.split() for line in composed) == 1, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "compositions: 3", proc.stderr  # the sweep's, and a job's each
    frames = sorted(json.loads(m.read_text())["num_frames"] for m in sweep_dir.glob("*/metrics.json"))
    assert frames == [3, 4]
