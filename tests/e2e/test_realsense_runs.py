"""`slamkit dataset=realsense` on a RealSense recording made here from the real TUM frames (no
camera): the TUM folder run's trajectory from a .db3 and from a ROS1 .bag, sequential and in
real time; at its recorded pace as
a live source (frames dropped while tracking is busy, counted; the viewers following it; Ctrl-C
ending it with every output written and the frames kept by `dataset.record` replayable); no
camera: exit 2 with one line. The dataset itself: tests/plugins/test_realsense.py."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys

import numpy as np
import pytest

from slamkit.formats.tum import read_tum_trajectory

from support.commands import Slamkit, run_slamkit
from support.data import TUM, require_data

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is the optional extra `realsense` (in `test`); "
                         "Intel publishes no wheel for this platform")

from slamkit_plugins.datasets.realsense.sdk import RECORDING_SUFFIXES  # noqa: E402

from support.realsense_writer import TumRecordings, write_tum_recording  # noqa: E402

N = 20
# tracker.extrapolation off in every run (null: 2 in real time): its thresholds (the cosine and
# growth of successive updates) turn the recording's rounding of depth and intrinsics (1e-7) into
# pose differences up to 2.4e-5 m, and this compares the frames the recording gives at 1e-6
COMMON = ["mapper=none", "output.progress=false", "output.plot=false", "dataset.depth_trunc=3.0", "dataset.prefetch=2",
          "tracker.extrapolation=0"]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    return TumRecordings(require_data(TUM), tmp_path_factory.mktemp("realsense"), N)


@pytest.fixture
def recording(recordings):
    return recordings(".db3")


def _run(tmp_path, name: str, *args: str):
    out = tmp_path / name
    proc = run_slamkit(*args, *COMMON, f"hydra.run.dir={out}", cwd=tmp_path, env_extra={"OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    return read_tum_trajectory(out / "trajectory.txt"), json.loads((out / "metrics.json").read_text()), out


@pytest.mark.parametrize("suffix", RECORDING_SUFFIXES)
def test_a_recording_left_playing_mid_file_does_not_abort_the_interpreters_exit(recordings, suffix):
    """A script that reads one frame set of a recording and exits without stopping it ends
    normally (the SDK's teardown met the playback still playing and aborted the process)."""
    script = ("import sys; from slamkit_plugins.datasets.realsense.stream import Stream; "
              "print(Stream(sys.argv[1]).next(5.0).number)")
    proc = subprocess.run([sys.executable, "-c", script, str(recordings(suffix))], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip(), proc.stderr[-2000:]


@pytest.mark.slow
@pytest.mark.parametrize("suffix", RECORDING_SUFFIXES)
def test_a_recording_gives_the_tum_folder_trajectory_sequential_and_in_real_time(tmp_path, tum_path, recordings,
                                                                                 suffix):
    recording = recordings(suffix)
    (t_folder, p_folder), m_folder, _ = _run(tmp_path, "folder", "dataset=tum", f"dataset.path={tum_path}",
                                             f"dataset.max_frames={N}")
    gt = f"dataset.groundtruth={tum_path / 'groundtruth.txt'}"
    for mode in (["mode=sequential"], ["mode=realtime", "realtime.fps_limit=30", "realtime.drop_frames=false"]):
        (t, p), m, _ = _run(tmp_path, mode[0].split("=")[1], "dataset=realsense", f"dataset.path={recording}", gt,
                            *mode)
        assert m["mode"] == mode[0].split("=")[1] and m["num_frames"] == N and m["dropped_frames"] == 0
        # the same frames, depth (raw / 5000) and intrinsics (the SDK's float32s as decimals): the same
        # poses, but for the first one, from the ground truth at a timestamp up to 2.4e-7 s off (the SDK's
        # milliseconds in a double)
        np.testing.assert_allclose(t, t_folder, atol=1e-6)
        np.testing.assert_allclose(p, p_folder, atol=1e-6)
        assert m["ate_rmse_m"] == pytest.approx(m_folder["ate_rmse_m"], abs=1e-9)  # ground truth <= 2.4e-7 s apart
    assert m_folder["ate_rmse_m"] < 0.05


@pytest.mark.slow
def test_at_its_recorded_pace_a_recording_is_a_live_source_the_viewers_follow(tmp_path, tum_path, recording):
    """recorded_pace: real time with realtime.drop_frames without asking; frames the tracker is busy for
    are dropped and counted (frames.csv, metrics.json); the frames it tracked reach the rerun
    recording and viser, as a recording's do."""
    pytest.importorskip("rerun", reason="rerun-sdk is the optional extra `viewer`")
    from support.rerun_rows import rrd_rows

    rrd = tmp_path / "live.rrd"
    (t, _), m, out = _run(tmp_path, "rerun", "dataset=realsense", f"dataset.path={recording}",
                          "dataset.recorded_pace=true", "viewer=rerun", f"viewer.save={rrd}")
    assert m["mode"] == "realtime" and m["settings"]["realtime.drop_frames"] is True
    with open(out / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    dropped = sum(row["note"] == "dropped" for row in rows)
    assert len(t) == len(rows) == m["num_frames"] <= N and dropped == m["dropped_frames"]
    tracked = m["num_frames"] - m["dropped_frames"]
    assert tracked >= 2
    assert np.all(np.diff(t) > 0)
    assert m["stream_time_s"] >= 0.8 * (t[-1] - t[0])  # paced by the recording, not as fast as tracked
    assert rrd_rows(rrd)[0]["/world/camera"] == tracked

    (_, _), m_viser, out_viser = _run(tmp_path, "viser", "dataset=realsense", f"dataset.path={recording}",
                                      "dataset.recorded_pace=true", "viewer=viser", "viewer.port=0")
    stats = json.loads((out_viser / "viser.json").read_text())
    # viser's worker sends the newest view when it is free (it skips views while busy): at least one
    assert 1 <= stats["updates"]["image"]["count"] <= m_viser["num_frames"] - m_viser["dropped_frames"]


@pytest.mark.slow
def test_ctrl_c_ends_a_live_source_with_every_output_written_and_its_frames_replayable(tmp_path, tum_path):
    """SIGINT during the stream of a recording at its pace: exit 130, trajectory, map, metrics
    (interrupted) written; the frames kept by dataset.record replay with dataset=folder."""
    recording = write_tum_recording(tum_path, tmp_path / "long.db3", 90)
    kept, out = tmp_path / "kept", tmp_path / "live"
    run = Slamkit("dataset=realsense", f"dataset.path={recording}", "dataset.recorded_pace=true",
                  f"dataset.record={kept}", "mapper=gaussian_splatting", "mapper.save_images=0",
                  "output.progress=false",
                  "output.plot=false", f"hydra.run.dir={out}", cwd=tmp_path, pause_at="stream@10",
                  env={"OMP_NUM_THREADS": "1"})
    run.wait_for("slamkit: paused at stream@10")
    run.send(signal.SIGINT)
    status, _, stderr = run.finish(120)
    assert status == 130, stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "interrupted" and m["num_frames"] >= 10
    t, _ = read_tum_trajectory(out / "trajectory.txt")
    assert len(t) == m["num_frames"] and (out / "map.ply").is_file() and (out / "frames.csv").is_file()
    listed = [line.split()[0] for line in (kept / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(listed) >= len(t) and {f"{s:.6f}" for s in t} <= set(listed)  # every frame it saw was kept
    (t_replay, _), m_replay, _ = _run(tmp_path, "replay", "dataset=folder", f"dataset.path={kept}",
                                      f"dataset.trajectory={tum_path / 'groundtruth.txt'}")
    assert m_replay["num_frames"] == len(listed) and m_replay["ate_rmse_m"] < 0.1


@pytest.mark.slow
def test_no_camera_is_one_line(tmp_path):
    proc = run_slamkit("dataset=realsense", "mapper=none", "output.progress=false", f"hydra.run.dir={tmp_path / 'run'}",
                       cwd=tmp_path)
    if "no RealSense camera connected" not in proc.stderr and proc.returncode == 0:
        pytest.skip("a RealSense camera is connected here")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("slamkit: error: no RealSense camera connected"), proc.stderr
