"""Nothing lost on any exit (issue 20) and the run's failure paths (issue 19), through the real
commands: a signal in each phase of a run (sent once the run says it has reached that phase,
`SLAMKIT_PAUSE_AT`), a signal during start-up, a run whose tracking failed, a full disk, peak
memory taken after the evaluation, and kill -9 at random moments. The parts that need no run
(StopSignals, slamkit-report on unfinished runs, an output folder that cannot be made):
tests/core/test_lifecycle.py."""

from __future__ import annotations

import csv
import errno
import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from slamkit.formats.checkpoint import CHECKPOINT_NAME, read_checkpoint, read_meta
from slamkit.formats.ply import load_ply
from slamkit.formats.tum import read_tum_trajectory
from slamkit.run.ownership import LOCK_NAME

from support.commands import Slamkit, run_slamkit, slamkit_in_process, tiny
from support.folders import tiny_tum
from support.plugins import make_plugin_dist

TINY_MAPPING = tuple(tiny())
CONTRACT_KEYS = {"num_frames", "num_keyframes", "fps", "tracking_fps", "tracking_time_s", "mapping_time_s",
                 "lost_frames", "completed", "ate_rmse_m", "ate_mean_m", "status", "phase", "error"}


def _metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


# -- issue 20 point 1: a signal in any phase keeps the outputs of the phases before it ----------

@pytest.mark.slow
@pytest.mark.parametrize("point,sig,phase", [("stream@3", signal.SIGINT, "stream"),
                                             ("refine", signal.SIGTERM, "refine"),
                                             ("map", signal.SIGINT, "map"), ("evaluate", signal.SIGTERM, "evaluate")])
def test_a_signal_in_each_phase_keeps_the_earlier_phases_outputs_and_the_map(point, sig, phase, tmp_path):
    out = tmp_path / "run"
    run = Slamkit(*TINY_MAPPING, f"hydra.run.dir={out}", cwd=tmp_path, pause_at=point)
    run.wait_for(f"slamkit: paused at {point}")
    run.send(sig)
    code, stdout, stderr = run.finish()
    assert code == 128 + sig, stderr[-3000:]
    assert "Traceback" not in stderr
    assert f"(incomplete: interrupted during {phase})" in stdout
    metrics = _metrics(out)
    assert CONTRACT_KEYS <= set(metrics)
    assert (metrics["completed"], metrics["status"], metrics["phase"]) == (False, "interrupted", phase)
    assert metrics["error"] == f"interrupted ({sig.name}) during {phase}"
    frames = 3 if phase == "stream" else 6
    timestamps, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(timestamps) == metrics["num_frames"] == frames and np.isfinite(poses).all()
    assert metrics["ate_rmse_m"] is not None  # the trajectory so far is a result
    assert len(load_ply(out / "map.ply")) == metrics["num_gaussians"] > 0  # the map trained so far
    assert "psnr" not in metrics and not list(out.glob("render_*.png"))  # the evaluation never ran
    assert metrics["refine_iterations"] == (0 if phase in ("stream", "refine") else 4)  # paused before the first
    saved = read_meta(out / CHECKPOINT_NAME)  # written where the map is: at the end of the refinement, or on the stop
    assert saved["reason"] == ("interrupted" if phase in ("stream", "refine") else "end")
    assert saved["num_frames"] == frames
    assert not list(out.glob(".*.tmp"))


@pytest.mark.slow
def test_a_completed_run_says_so_and_takes_peak_memory_after_the_evaluation(tmp_path):
    """A mapper whose evaluation holds 400 MB: peak_memory_mb sees it (it was read before the
    evaluation, so it did not); the phases' files are all there."""
    site = make_plugin_dist(tmp_path / "site", "slamkit-hungry-mapper", {"hungry_mapper": HUNGRY_MAPPER},
                            {"hungry": "hungry_mapper"})
    out = tmp_path / "run"
    proc = run_slamkit("dataset.num_frames=8", "mapper=hungry", "output.progress=false", f"hydra.run.dir={out}",
                       cwd=tmp_path, env_extra={"PYTHONPATH": str(site)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = _metrics(out)
    assert (metrics["completed"], metrics["status"], metrics["phase"]) == (True, "completed", "done")
    assert metrics["error"] is None
    assert metrics["held_mb"] == 400
    rss = [float(r["rss_mb"]) for r in csv.DictReader(open(out / "frames.csv"))]
    assert metrics["peak_memory_mb"] > max(rss) + 300
    assert metrics["map_saved_before"] is True and (out / "hungry_map.txt").read_text() == "saved"


HUNGRY_MAPPER = """
import numpy as np
from dataclasses import dataclass
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Mapper, PluginConfig

@dataclass
class HungryConfig(PluginConfig):
    held_mb: int = 400

class HungryMapper(Mapper):
    def __init__(self, cfg, context=None):
        self.cfg, self.frames = cfg, 0

    def add_keyframe(self, frame, pose, kind, new_rows):
        pass

    def optimize(self, iterations):
        return 0

    def save_map(self, out_dir):
        path = out_dir / "hungry_map.txt"
        path.write_text("saved")
        return [path]

    def evaluate(self, frames, poses, out_dir):
        held = np.ones(self.cfg.held_mb * 2**20, dtype=np.uint8)  # written: resident
        return {"held_mb": int(held.sum()) // 2**20, "map_saved_before": (out_dir / "hungry_map.txt").exists()}

@hookimpl
def slamkit_plugins():
    return [PluginSpec("hungry", HungryMapper, HungryConfig)]
"""


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_startup_is_one_line_and_status_128_plus_its_number(sig, tmp_path):
    out = tmp_path / "run"
    run = Slamkit("output.progress=false", f"hydra.run.dir={out}", cwd=tmp_path, pause_at="startup")
    run.wait_for("slamkit: paused at startup")
    run.send(sig)
    code, stdout, stderr = run.finish()
    assert code == 128 + sig
    assert stderr.strip().splitlines()[-1] == f"slamkit: interrupted ({sig.name}) during start-up"
    assert "Traceback" not in stderr and not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("delay_s", [1.0, 2.5])
def test_sigint_while_plugins_load_prints_no_traceback(delay_s, tmp_path):
    """No hook: SIGINT at a fixed time after the start, while torch and the plugins import."""
    run = Slamkit("output.progress=false", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    time.sleep(delay_s)
    run.send(signal.SIGINT)
    code, stdout, stderr = run.finish()
    assert code == 130 and "Traceback" not in stderr, stderr[-3000:]
    if "(incomplete: interrupted during " not in stdout:  # an unloaded machine may have reached the stream
        assert stderr.strip().splitlines()[-1].startswith("slamkit: interrupted (SIGINT) during ")


# -- issue 20 point 2: a run that tracked no frame, or lost too many, has failed ---------------

@pytest.mark.slow
def test_a_run_that_tracks_no_frame_fails_with_no_ate(tmp_path):
    out = tmp_path / "run"
    proc = run_slamkit("dataset.num_frames=10", "dataset.depth_trunc=1e-6", "output.progress=false",
                       f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 3, proc.stdout + proc.stderr[-3000:]
    assert "ATE RMSE not reported" in proc.stdout and "(failed: tracking failed: no frame tracked" in proc.stdout
    metrics = _metrics(out)
    assert (metrics["completed"], metrics["status"]) == (False, "failed")
    assert metrics["error"] == "tracking failed: no frame tracked (10 of 10 frames lost)"
    assert metrics["ate_rmse_m"] is None and metrics["rpe_trans_rmse_m"] is None and metrics["lost_fraction"] == 1.0
    assert len(read_tum_trajectory(out / "trajectory.txt")[0]) == 10


@pytest.mark.slow
def test_losing_more_than_max_lost_fraction_fails_the_run(tum_path, tmp_path):
    """12 TUM frames of which 4 colour images are unreadable (dataset.on_error=skip): 4/12 lost
    fails with eval.max_lost_fraction=0.25, and is a result with the default 0.5."""
    seq = tiny_tum(tmp_path / "rgbd_dataset_freiburg1_x", frames=12)
    rgb = [line.split()[1] for line in (seq / "rgb.txt").read_text().splitlines()]
    for i in (3, 5, 7, 9):
        (seq / rgb[i]).write_bytes(b"not a png")
    args = ("dataset=tum", f"dataset.path={seq}", "dataset.on_error=skip", "mapper=none", "output.progress=false")
    failed = run_slamkit(*args, "eval.max_lost_fraction=0.25", f"hydra.run.dir={tmp_path / 'strict'}", cwd=tmp_path)
    assert failed.returncode == 3, failed.stderr[-3000:]
    metrics = _metrics(tmp_path / "strict")
    assert metrics["error"] == "tracking failed: 4 of 12 frames lost, more than eval.max_lost_fraction=0.25"
    assert metrics["ate_rmse_m"] is None and metrics["lost_fraction"] == pytest.approx(4 / 12)
    ok = run_slamkit(*args, f"hydra.run.dir={tmp_path / 'default'}", cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr[-3000:]
    assert _metrics(tmp_path / "default")["ate_rmse_m"] is not None


@pytest.mark.slow
def test_a_sweep_goes_on_past_a_failed_run_and_the_report_keeps_it_apart(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_slamkit("-m", "dataset.depth_trunc=1e-6,5", "dataset.num_frames=8", "output.progress=false",
                       f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert proc.returncode == 3, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("slamkit: error: tracking failed in 1 of the sweep's runs: ")
    assert sorted(_metrics(d)["status"] for d in sweep.iterdir() if d.is_dir()) == ["completed", "failed"]
    exe = Path(sys.executable).with_name("slamkit-report")
    report = subprocess.run([str(exe), str(sweep)], capture_output=True, text=True)
    assert report.returncode == 0, report.stderr
    rows = {r["dataset.depth_trunc"]: r for r in csv.DictReader(open(sweep / "report.csv"))}
    assert rows["5"]["status"] == "completed" and float(rows["5"]["ate_rmse_m"]) < 0.05
    assert rows["1e-06"]["status"] == "failed" and rows["1e-06"]["ate_rmse_m"] == ""
    assert rows["1e-06"]["error"].startswith("tracking failed: no frame tracked")


# -- issue 19: a full disk -----------------------------------------------------------------------

def _fail_fsync_of(monkeypatch, name: str | None) -> None:
    """os.fsync fails with ENOSPC (a full disk) for the atomic writes of `name` (None: of every
    file: their temporary files are .NAME.XXXX.tmp)."""
    fsync = os.fsync

    def failing(fd):
        temporary = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        if temporary.startswith(f".{name}.") or (name is None and temporary.endswith(".tmp")):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return fsync(fd)

    monkeypatch.setattr(os, "fsync", failing)


@pytest.mark.slow
def test_a_full_disk_while_writing_the_map_keeps_the_rest_and_says_so(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    _fail_fsync_of(monkeypatch, "map.ply")
    code, stdout, stderr = slamkit_in_process(monkeypatch, capsys, *TINY_MAPPING, f"hydra.run.dir={out}")
    assert code == 1 and "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == (
        f"slamkit: error: could not write {out / 'map.ply'}: No space left on device; kept in {out}: camera.json, "
        "trajectory.txt, keyframes.txt, groundtruth.txt, metrics.json, trajectory.png")
    metrics = _metrics(out)
    assert (metrics["completed"], metrics["status"], metrics["phase"]) == (False, "failed", "map")
    assert metrics["error"] == "OSError: [Errno 28] No space left on device"
    assert len(read_tum_trajectory(out / "trajectory.txt")[0]) == metrics["num_frames"] == 6
    assert not (out / "map.ply").exists() and not list(out.glob(".*.tmp"))


@pytest.mark.slow
def test_a_full_disk_for_every_file_is_still_one_line(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    _fail_fsync_of(monkeypatch, None)
    code, stdout, stderr = slamkit_in_process(monkeypatch, capsys, "dataset.num_frames=5", "output.progress=false",
                                               f"hydra.run.dir={out}")
    assert code == 1 and "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == (f"slamkit: error: could not write {out / 'camera.json'} (and 3 more): "
                                               f"No space left on device; kept in {out}: nothing")
    # camera.json failed at the stream's start; then trajectory.txt, keyframes.txt, metrics.json
    assert not (out / "metrics.json").exists() and not list(out.glob(".*.tmp"))


@pytest.mark.slow
def test_a_file_size_limit_keeps_the_small_files(tmp_path):
    """A real write failure (RLIMIT_FSIZE: EFBIG past 64 KB): map.ply does not fit, the
    trajectory and metrics.json do, and the run says which."""
    out = tmp_path / "run"
    warm = run_slamkit(*tiny(final_iterations=0), f"hydra.run.dir={tmp_path / 'warm'}", cwd=tmp_path)
    assert warm.returncode == 0, warm.stderr[-3000:]  # caches (the synthetic sequence) written without the limit

    def limit():
        import resource

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))

    exe = Path(sys.executable).with_name("slamkit")
    proc = subprocess.run([str(exe), *tiny(mapper__save_images=0), "output.plot=false", f"hydra.run.dir={out}"],
                          cwd=tmp_path, capture_output=True, text=True, preexec_fn=limit, timeout=600)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"slamkit: error: could not write {out / 'map.ply'}: File too large; kept in {out}: ")
    assert "trajectory.txt" in last and "metrics.json" in last
    metrics = _metrics(out)
    assert (metrics["status"], metrics["phase"]) == ("failed", "map")
    assert len(read_tum_trajectory(out / "trajectory.txt")[0]) == 6 and not (out / "map.ply").exists()


# -- issue 19 point 4: kill -9 at random moments leaves every file whole or absent --------------

OUTPUT_NAMES = {"trajectory.txt", "keyframes.txt", "groundtruth.txt", "metrics.json", "camera.json", "map.ply",
                "frames.csv", "trajectory.png", "slamkit.log", CHECKPOINT_NAME}


def _check_whole(out: Path) -> list[str]:
    """Every file in a run folder killed at any moment: whole (it parses), or absent. frames.csv and
    slamkit.log are logs appended line by line: only a last line without its end may be cut."""
    seen = []
    for path in sorted(p for p in out.rglob("*") if p.is_file()):
        name = path.name
        if name.startswith(".") and name.endswith(".tmp"):
            continue  # an atomic write's temporary file, never renamed: not an output
        if name == LOCK_NAME:
            continue  # the run folder's lock (slamkit.run.ownership), not an output
        seen.append(name)
        if path.parent.name == ".hydra":
            assert isinstance(yaml.safe_load(path.read_text()), (dict, list)), path
            continue
        assert name in OUTPUT_NAMES or re.fullmatch(r"render_\d{4}\.png", name), path
        if name.endswith(".txt"):
            timestamps, poses = read_tum_trajectory(path)
            assert np.isfinite(poses).all()
        elif name.endswith(".json"):
            data = json.loads(path.read_text())
            assert isinstance(data, dict) and (name != "metrics.json" or CONTRACT_KEYS <= set(data))
        elif name == "map.ply":
            load_ply(path)
        elif name == CHECKPOINT_NAME:
            read_checkpoint(path)  # CRC-checked: whole
        elif name.endswith(".png"):
            from PIL import Image

            with Image.open(path) as im:
                im.load()
        elif name == "frames.csv":
            text = path.read_text()
            lines = text.split("\n")
            whole = lines[:-1]  # the last piece has no line end: it may be cut
            rows = list(csv.reader(whole))
            assert all(len(row) == len(rows[0]) for row in rows), path  # as many fields as the header
    return seen


def _stream_start(run: Slamkit, out: Path) -> float:
    """Wait until the run's stream starts (camera.json written); the time it did."""
    while not (out / "camera.json").exists():
        if run.proc.poll() is not None:
            pytest.fail(f"slamkit ended before its stream: {''.join(run.stderr)[-3000:]}")
        time.sleep(0.01)
    return time.monotonic()


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["sequential", "realtime"])
def test_kill_9_at_random_moments_leaves_every_file_whole_or_absent(mode, tmp_path):
    """Ten kills at moments drawn uniformly over the run after its start-up (stream, refinement,
    map, evaluation, the writes between them), as long as a calibration run took."""
    args = tiny(dataset__num_frames=12, final_iterations=200, mode=mode)
    calibration = tmp_path / "calibration"
    first = Slamkit(*args, f"hydra.run.dir={calibration}", cwd=tmp_path)
    start = _stream_start(first, calibration)
    code, _, stderr = first.finish()
    duration = time.monotonic() - start
    assert code == 0 and _metrics(calibration)["completed"], stderr[-3000:]
    _check_whole(calibration)
    outcomes = []
    for seed in range(10):
        out = tmp_path / f"kill{seed}"
        delay = random.Random(seed).uniform(0, duration)
        run = Slamkit(*args, f"hydra.run.dir={out}", cwd=tmp_path)
        time.sleep(max(0.0, _stream_start(run, out) + delay - time.monotonic()))
        run.proc.kill()
        run.finish()
        seen = _check_whole(out)
        status = f"{_metrics(out)['status']}@{_metrics(out)['phase']}" if "metrics.json" in seen else "-"
        outcomes.append(f"{delay:.1f}s:{status}:{'map' if 'map.ply' in seen else '-'}")
    print(f"kill -9 ({mode}; stream start to exit {duration:.1f} s): " + " ".join(outcomes))


# -- issue 41 point 3: a run that fails after the stream keeps a checkpoint to resume from -------

FAILING_FINISH_MAPPER = """
from dataclasses import dataclass
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig
from slamkit_plugins.mappers.none import NoMapper

@dataclass
class FinishConfig(PluginConfig):
    keep_untrackable: bool = False
    fail: bool = True

class FailingFinishMapper(NoMapper):
    def finish(self):
        if self.cfg.fail:
            raise RuntimeError("finish broke")

@hookimpl
def slamkit_plugins():
    return [PluginSpec("failing_finish", FailingFinishMapper, FinishConfig)]
"""


@pytest.mark.slow
def test_a_run_that_fails_after_the_stream_writes_a_checkpoint_that_resumes(tmp_path):
    site = make_plugin_dist(tmp_path / "site", "slamkit-failing-finish", {"failing_finish": FAILING_FINISH_MAPPER},
                            {"failing_finish": "failing_finish"})
    env = {"PYTHONPATH": str(site)}
    out = tmp_path / "run"
    proc = run_slamkit("dataset.num_frames=8", "mapper=failing_finish", "output.progress=false", f"hydra.run.dir={out}",
                       cwd=tmp_path, env_extra=env)
    assert proc.returncode != 0 and "finish broke" in proc.stderr.strip().splitlines()[-1]
    assert _metrics(out)["status"] == "failed"
    meta = read_meta(out / CHECKPOINT_NAME)
    assert (meta["reason"], meta["completed"], meta["num_frames"]) == ("failed", False, 8)
    resumed = run_slamkit(f"resume={out}", "mapper.fail=false", cwd=tmp_path, env_extra=env)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    metrics = _metrics(out)
    assert (metrics["status"], metrics["num_frames"]) == ("completed", 8)
