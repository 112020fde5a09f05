"""Sweeps beyond joblib: hydra/launcher=ray on a local Ray cluster (the same results as a joblib
sweep of the same grid, read by slamkit-report, nothing left behind) and the hyper-parameter
search +experiment=search_gicp through the Optuna sweeper (failed runs scored, the study goes on)."""

from __future__ import annotations

import csv
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
import yaml

from slamkit.cli.report import main as report_main

from support.commands import run_slamkit

pytestmark = pytest.mark.slow  # every test here starts the slamkit command

GRID = ["tracker=gicp,kiss_icp", "dataset=synthetic", "dataset.num_frames=10", "dataset.width=160",
        "dataset.height=120", "mapper=none", "output.progress=false", "output.plot=false"]


def _processes_mentioning(text: str) -> list[str]:
    """Command lines of running processes that contain `text`."""
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit() and int(pid) != os.getpid():
            try:
                cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if text in cmdline:
                found.append(f"{pid}: {cmdline[:200]}")
    return found


def _stop_cluster(marker: str) -> None:
    """Stop the Ray cluster whose processes' command lines mention `marker` (its temporary
    folder), and their children (Ray's agents), by process id: `ray stop` would stop every Ray
    cluster of the machine."""
    import signal
    import time

    def family() -> set[int]:
        pids = {int(line.split(":")[0]) for line in _processes_mentioning(marker)}
        parents = {}
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                state, parent = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[:2]
            except (OSError, ValueError):
                continue
            if state != "Z":  # a zombie is gone already, waiting for its parent
                parents[int(pid)] = int(parent)
        pids &= set(parents)
        grown = True
        while grown:
            children = {pid for pid, parent in parents.items() if parent in pids} - pids
            grown = bool(children)
            pids |= children
        return pids

    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in family():
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 15
        while family() and time.monotonic() < deadline:
            time.sleep(0.2)


def _jobs(sweep: Path) -> dict[str, tuple[bytes, dict]]:
    """tracker -> (trajectory.txt bytes, metrics) of each job of a sweep."""
    import json

    jobs = {}
    for metrics in sorted(sweep.glob("*/metrics.json")):
        overrides = yaml.safe_load((metrics.parent / ".hydra" / "overrides.yaml").read_text())
        tracker = next(o.split("=")[1] for o in overrides if o.startswith("tracker="))
        jobs[tracker] = ((metrics.parent / "trajectory.txt").read_bytes(), json.loads(metrics.read_text()))
    return jobs


@pytest.fixture
def short_cache():
    """A project cache with a short path: Ray's socket paths inside it must stay under 108 bytes,
    which pytest's deep temporary folders exceed."""
    path = Path(tempfile.mkdtemp(prefix="sk", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


def test_a_ray_sweep_gives_the_joblib_sweeps_results_and_leaves_nothing_behind(tmp_path, short_cache):
    pytest.importorskip("ray", reason="ray is the optional extra `ray` (in `test`)")
    home, tmpdir, cache = tmp_path / "home", tmp_path / "tmpdir", short_cache
    for d in (home, tmpdir):
        d.mkdir()
    env = {"HOME": str(home), "TMPDIR": str(tmpdir), "SLAMKIT_CACHE": str(cache), "OMP_NUM_THREADS": "1"}
    env.pop("RAY_AUTH_MODE", None)
    tmp_ray_before = set(Path("/tmp").glob("ray*"))
    sweeps = {}
    for launcher, extra in (("joblib", ["hydra.launcher.n_jobs=2"]), ("ray", [])):
        sweeps[launcher] = tmp_path / launcher
        proc = run_slamkit("-m", *GRID, f"hydra/launcher={launcher}", *extra, f"hydra.sweep.dir={sweeps[launcher]}",
                           cwd=tmp_path, env_extra=env, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
    joblib_jobs, ray_jobs = _jobs(sweeps["joblib"]), _jobs(sweeps["ray"])
    assert sorted(ray_jobs) == sorted(joblib_jobs) == ["gicp", "kiss_icp"]
    for tracker, (trajectory, metrics) in ray_jobs.items():
        assert trajectory == joblib_jobs[tracker][0], tracker  # the same poses, as written (1e-9 m)
        assert metrics["ate_rmse_m"] == pytest.approx(joblib_jobs[tracker][1]["ate_rmse_m"], rel=1e-9)
        assert metrics["num_keyframes"] == joblib_jobs[tracker][1]["num_keyframes"]
        assert metrics["ate_rmse_m"] < 0.05
    assert report_main([str(sweeps["ray"])]) == 0
    rows = {r["tracker"]: r for r in csv.DictReader(open(sweeps["ray"] / "report.csv"))}
    assert sorted(rows) == ["gicp", "kiss_icp"]
    assert float(rows["gicp"]["ate_rmse_m"]) == pytest.approx(ray_jobs["gicp"][1]["ate_rmse_m"])
    # nothing outside the sweep folders and the project cache, and no Ray process left
    assert not any(home.iterdir()), sorted(home.rglob("*"))[:5]
    assert set(Path("/tmp").glob("ray*")) == tmp_ray_before
    assert (cache / "ray").is_dir()  # Ray's session folder went into the project cache
    assert not _processes_mentioning(str(cache / "ray"))


def test_ray_launcher_on_an_existing_cluster_by_address(tmp_path):
    """`ray start --head` first, then the sweep connects with hydra.launcher.ray.init.address."""
    pytest.importorskip("ray", reason="ray is the optional extra `ray` (in `test`)")
    ray_exe = Path(os.sys.executable).with_name("ray")
    temp = Path(tempfile.mkdtemp(prefix="skc", dir="/tmp"))  # short: Ray's socket paths are inside
    env = dict(os.environ, RAY_AUTH_MODE="disabled", HOME=str(tmp_path))
    start = subprocess.run([str(ray_exe), "start", "--head", "--port=0", f"--temp-dir={temp}", "--num-cpus=2",
                            "--include-dashboard=false", "--disable-usage-stats"],
                           env=env, capture_output=True, text=True, timeout=120)
    try:
        assert start.returncode == 0, start.stderr[-2000:]
        address = re.search(r"--address='([^']+)'", start.stdout + start.stderr).group(1)
        sweep = tmp_path / "sweep"
        proc = run_slamkit("-m", *GRID, "hydra/launcher=ray", f"hydra.launcher.ray.init.address={address}",
                           f"hydra.sweep.dir={sweep}", cwd=tmp_path,
                           env_extra={"RAY_AUTH_MODE": "disabled", "OMP_NUM_THREADS": "1"}, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert sorted(_jobs(sweep)) == ["gicp", "kiss_icp"]
    finally:
        _stop_cluster(str(temp))
        leftover = _processes_mentioning(str(temp))
        shutil.rmtree(temp, ignore_errors=True)
    assert not leftover


def test_the_optuna_search_scores_failed_runs_and_finds_the_best(tmp_path):
    """Three trials over a correspondence distance that is either valid or rejected by the
    tracker's config (the seeded sampler draws both): the rejected ones score
    objective.failed_value and the study completes with the valid one as the best."""
    pytest.importorskip("optuna", reason="optuna is the optional extra `optuna` (in `test`)")
    sweep = tmp_path / "search"
    proc = run_slamkit("+experiment=search_gicp", "dataset=synthetic", "dataset.num_frames=8", "dataset.width=160",
                       "dataset.height=120", "output.progress=false", "output.plot=false",
                       "hydra/sweeper/sampler=random",
                       "hydra.sweeper.sampler.seed=0", "hydra.sweeper.n_trials=3",
                       "tracker.max_correspondence_distance=choice(0.05,-1.0)",
                       "keyframe.keyframe_threshold=choice(0.8)", f"hydra.sweep.dir={sweep}",
                       cwd=tmp_path, env_extra={"OMP_NUM_THREADS": "1"}, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    said = proc.stdout + proc.stderr
    assert "tracker.max_correspondence_distance: expected" in said  # the rejected value, in one line
    assert "the run failed; its score is objective.failed_value = 1.0" in said
    result = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert result["best_params"]["tracker.max_correspondence_distance"] == 0.05
    assert 0 < result["best_value"] < 0.05  # the ATE of a valid run, in metres
    assert len(list(sweep.glob("*/.hydra/overrides.yaml"))) == 3
    assert len(list(sweep.glob("*/metrics.json"))) == 1  # the rejected runs never started
    assert report_main([str(sweep)]) == 0  # the completed trials
