"""`dataset=realsense` without a camera: a RealSense recording (a .db3 written with pyrealsense2's
software device, a ROS1 .bag written with rosbags in the SDK's layout, both from the real TUM
frames, tests/support/realsense_writer.py) read back as the
TUM dataset reads the folder, frame by frame and at its recorded pace; `dataset.record` keeping
the frames in the TUM layout; the device enumeration and the one-line errors (no camera, no
library, bad files). From the command line: tests/e2e/test_realsense_runs.py."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

from slamkit.errors import ConfigError, DataError
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import discover
from slamkit.registry.schema import Mode
from slamkit.roles import Dataset, SourceEnded

from support.data import TUM, require_data

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is the optional extra `realsense` (in `test`); "
                         "Intel publishes no wheel for this platform")

from slamkit_plugins.datasets.folder import FolderConfig, FolderDataset  # noqa: E402
from slamkit_plugins.datasets.realsense import (  # noqa: E402
    RealSenseConfig,
    RealSenseDataset,
    sdk,  # noqa: E402
)
from slamkit_plugins.datasets.realsense.bag import write_bag_recording  # noqa: E402
from slamkit_plugins.datasets.realsense.stream import Stream  # noqa: E402
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset  # noqa: E402

from support.realsense_writer import TUM_UNITS_PER_METRE, TumRecordings  # noqa: E402

N = 8
#: metres: both read depth as raw / 5000 (the device scale read as its shortest decimal, 0.0002 m)
DEPTH_ROUNDING = 0.0
#: seconds: the SDK keeps a timestamp as milliseconds in a double, whose step at TUM's 1.3e12 ms
#: is 2.4e-4 ms (2.4e-7 s); read back, a timestamp is within that of the one written (.bag, .db3)
TIMESTAMP_ROUNDING = 1e-6
#: the ground truth interpolated at a timestamp up to 2.4e-7 s off: a pose element within this
GT_ROUNDING = 1e-6
#: passes over a recording, each of which must give every frame set
PASSES = 5
#: the fraction of pixels whose depth `rs.align` between identical cameras leaves as it was (0.988 to 0.994 seen)
ALIGNED_SAME = 0.97


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    return TumRecordings(require_data(TUM), tmp_path_factory.mktemp("realsense"), N)


@pytest.fixture
def recording(recordings):
    return recordings(".db3")


def _tum(**kw) -> TUMDataset:
    return TUMDataset(TUMConfig(path=str(TUM), max_frames=N, **kw))


def _same_frame(got, want) -> None:
    assert got.timestamp == pytest.approx(want.timestamp, abs=TIMESTAMP_ROUNDING)
    np.testing.assert_array_equal(np.asarray(got.rgb), np.asarray(want.rgb))
    np.testing.assert_allclose(got.depth, want.depth, atol=DEPTH_ROUNDING, rtol=0)
    np.testing.assert_allclose(got.gt_pose, want.gt_pose, atol=GT_ROUNDING, rtol=0)


def test_realsense_is_a_registered_dataset():
    spec = discover().get("dataset", "realsense")
    assert issubclass(spec.cls, Dataset) and spec.config is RealSenseConfig


@pytest.mark.parametrize("suffix", sdk.RECORDING_SUFFIXES)
def test_recording_frames_equal_the_tum_folder_frames(recordings, suffix):
    """Intrinsics and depth scale from the recording (a .db3, a .bag), every frame set in order,
    then an earlier frame again (played from the start)."""
    recording = recordings(suffix)
    ds = RealSenseDataset(RealSenseConfig(path=str(recording), groundtruth=str(TUM / "groundtruth.txt")))
    ref = _tum()
    try:
        assert not ds.live and len(ds) == len(ref) == N
        cam, want = ds.camera, ref.camera
        assert (cam.width, cam.height) == (want.width, want.height)
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == (want.fx, want.fy, want.cx, want.cy)  # the float32s as decimals
        assert ds.units_per_metre == 5000.0
        assert not ds.stream.aligned  # registered to colour in the recording: used as it is
        for i in (*range(N), 2, 0):
            _same_frame(ds[i], ref[i])
    finally:
        ds.close()


@pytest.mark.parametrize("suffix", sdk.RECORDING_SUFFIXES)
def test_every_pass_over_a_recording_gives_every_frame_set(recordings, suffix):
    """Frame by frame, a recording's playback gives all its frame sets, each once and in order,
    on every pass (through the SDK's pipeline a .bag's first one was lost in about 1 pass of 40
    on a busy machine, which made CI's runs one frame short: these few passes catch that rarely)."""
    recording, want = recordings(suffix), [_tum().timestamp(i) for i in range(N)]
    for _ in range(PASSES):
        stream = Stream(recording)
        try:
            got = [frames.timestamp for frames in iter(lambda: stream.next(5.0), None)]
        finally:
            stream.stop()
        np.testing.assert_allclose(got, want, atol=TIMESTAMP_ROUNDING, rtol=0)


def test_a_colour_stream_that_starts_late_and_drops_frames_gives_the_frame_sets_with_both(tmp_path):
    """A camera's recording can start its colour after its depth and lose colour frames: the
    frame sets with both are read, each with its own depth, the depth frames alone passed over
    (here depth runs 6 and 7 frames ahead of colour, more than the playback holds for the reader)."""
    n, colour = 20, [*range(6, 10), *range(17, 20)]
    ref = TUMDataset(TUMConfig(path=str(require_data(TUM)), max_frames=n))
    recording = write_bag_recording(ref, tmp_path / "late_colour.bag", TUM_UNITS_PER_METRE, color_frames=colour)
    ds = RealSenseDataset(RealSenseConfig(path=str(recording)))
    try:
        assert len(ds) == len(colour)
        for i, k in enumerate(colour):
            got, want = ds[i], ref[k]
            assert got.timestamp == pytest.approx(want.timestamp, abs=TIMESTAMP_ROUNDING)
            np.testing.assert_array_equal(np.asarray(got.rgb), np.asarray(want.rgb))
            np.testing.assert_allclose(got.depth, want.depth, atol=DEPTH_ROUNDING, rtol=0)
    finally:
        ds.close()


@pytest.mark.parametrize("suffix", sdk.RECORDING_SUFFIXES)
def test_depth_the_sdk_aligns_to_colour_is_each_frames_own(recordings, suffix, monkeypatch):
    """Depth the SDK reprojects into the colour camera (`rs.align`; here between identical
    cameras, where only its resampling at depth edges changes a pixel) is each frame's own, the
    first included (the SDK gives the first colour and depth frames apart; the reader pairs them)."""
    monkeypatch.setattr("slamkit_plugins.datasets.realsense.stream._same_camera", lambda depth, color: False)
    ds = RealSenseDataset(RealSenseConfig(path=str(recordings(suffix))))
    ref = _tum()
    try:
        assert ds.stream.aligned and len(ds) == N
        for i in range(N):
            got = ds[i]
            assert got.timestamp == pytest.approx(ref.timestamp(i), abs=TIMESTAMP_ROUNDING)
            np.testing.assert_array_equal(np.asarray(got.rgb), np.asarray(ref[i].rgb))
            assert np.mean(got.depth == ref[i].depth) > ALIGNED_SAME  # another frame's: about 0.3
    finally:
        ds.close()


@pytest.mark.parametrize("skipped_passes, plays", [(1, True), (1000, False)])
def test_a_frame_set_the_sdk_skips_is_played_again_or_named(recording, monkeypatch, skipped_passes, plays):
    """The SDK's playback can skip a frame set on a busy machine: frame i must not become
    another frame's. Skipped once, the file is played again from its start and every frame is
    its own; skipped on every pass, a one-line error names the frame set."""
    ds = RealSenseDataset(RealSenseConfig(path=str(recording), groundtruth=str(TUM / "groundtruth.txt")))
    ref = _tum()
    honest, left = Stream.next, [skipped_passes]

    def skipping(stream, timeout):
        frames = honest(stream, timeout)
        if frames is not None and left[0] and abs(frames.timestamp - ds.file_stamps[3]) < TIMESTAMP_ROUNDING:
            left[0] -= 1
            frames = honest(stream, timeout)  # frame set 3 never came: set 4 in its place
        return frames

    monkeypatch.setattr(Stream, "next", skipping)
    try:
        if plays:
            for i in range(N):
                _same_frame(ds[i], ref[i])
            assert left == [0]
        else:
            with pytest.raises(DataError, match=r"frame set 3 came with timestamp [\d.]+ s, expected [\d.]+ s "
                                                r"\(the SDK skipped frame sets on \d+ passes\)"):
                for i in range(N):
                    ds[i]
    finally:
        ds.close()


@pytest.mark.parametrize("recorded_pace", [False, True])
@pytest.mark.parametrize("missed", [1, 2])
def test_a_first_frame_set_the_start_up_pass_missed_is_found_again_or_passed_over(recording, monkeypatch,
                                                                                   recorded_pace, missed):
    """The SDK's first pass over a file can lose its first frame set (CI saw a .bag's go): the
    start-up reads the second pass's first frame set and keeps it (missed once: every frame);
    missed by that read too, the recording is the frame sets the start-up saw, the missed one
    passed over on every later pass; at the recorded pace it can come live, and read again once
    passed it is itself, found by its timestamp, not the frame set after it."""
    ref = _tum()
    honest, left = Stream.next, [missed]

    def missing_the_first(stream, timeout):
        frames = honest(stream, timeout)
        if frames is not None and left[0] and abs(frames.timestamp - ref.timestamp(0)) < TIMESTAMP_ROUNDING:
            left[0] -= 1
            frames = honest(stream, timeout)  # frame set 0 never came
        return frames

    monkeypatch.setattr(Stream, "next", missing_the_first)
    ds = RealSenseDataset(RealSenseConfig(path=str(recording), recorded_pace=recorded_pace,
                                          groundtruth=str(TUM / "groundtruth.txt")))
    try:
        assert left == [0]
        first = missed - 1  # the first frame set the recording has
        assert ds.file_stamps[0] == pytest.approx(ref.timestamp(first), abs=TIMESTAMP_ROUNDING)
        if not recorded_pace:
            assert len(ds) == N - first
            for i in (*range(N - first), 2, 0):
                _same_frame(ds[i], ref[i + first])
            return
        for i in (0, 1):  # the lost frame set came live (which one it is: the recorded-pace test checks the rest)
            live = ds[i]
            assert live.timestamp == pytest.approx(ref.timestamp(i), abs=TIMESTAMP_ROUNDING)
            np.testing.assert_array_equal(np.asarray(live.rgb), np.asarray(ref[i].rgb))
        _same_frame(ds[0], ref[0])  # passed: read again from the file by its own timestamp
    finally:
        ds.close()


def test_a_recording_whose_times_go_back_is_one_line(recording, monkeypatch):
    honest, read = Stream.next, [0]

    def going_back(stream, timeout):
        frames = honest(stream, timeout)
        read[0] += 1
        return frames if frames is None or read[0] != 3 else dataclasses.replace(frames, timestamp=frames.timestamp - 1)

    monkeypatch.setattr(Stream, "next", going_back)
    with pytest.raises(DataError, match=r"^RealSense recording .*fr1\.db3: frame set 2's colour timestamp [\d.]+ s is "
                                        r"not after frame set 1's [\d.]+ s \(expected a recording whose device times "
                                        r"increase\)$"):
        RealSenseDataset(RealSenseConfig(path=str(recording)))


def test_a_recording_without_a_frame_set_is_one_line(recording, monkeypatch):
    monkeypatch.setattr(Stream, "next", lambda stream, timeout: None)
    with pytest.raises(DataError, match=r"^RealSense recording .*fr1\.db3 has no frame with both colour and depth "
                                        r"\(expected a recording of a colour and a depth stream\)$"):
        RealSenseDataset(RealSenseConfig(path=str(recording)))


@pytest.mark.parametrize("suffix", sdk.RECORDING_SUFFIXES)
def test_recorded_pace_gives_frames_as_they_come_and_ends(recordings, suffix, tmp_path):
    """recorded_pace: a live source (frames arrive in order on the recording's clock: a .db3's
    recorder times, a .bag's message times); each frame is the TUM frame of its timestamp;
    after the last one, SourceEnded; a passed frame is read again from the file; record=DIR
    keeps them in the TUM layout, which dataset=folder reads back."""
    recording = recordings(suffix)
    ds = RealSenseDataset(RealSenseConfig(path=str(recording), recorded_pace=True, record=str(tmp_path / "rec"),
                                          groundtruth=str(TUM / "groundtruth.txt")))
    ref = _tum()
    by_time = {round(ref.timestamp(i), 6): i for i in range(len(ref))}
    try:
        assert ds.live
        frames = []
        with pytest.raises(SourceEnded):
            while True:
                frames.append(ds[len(frames)])
        assert len(frames) + ds.source_dropped == N  # the SDK drops a frame set only where it counts it
        assert len(frames) >= N // 2
        arrivals = [ds.arrival(i) for i in range(len(frames))]
        assert all(a is not None for a in arrivals) and arrivals == sorted(arrivals)
        span = ref.timestamp(by_time[round(frames[-1].timestamp, 6)]) - ref.timestamp(by_time[round(
            frames[0].timestamp, 6)])
        assert arrivals[-1] - arrivals[0] >= 0.5 * span  # paced by the recording, not as fast as read
        for frame in frames:
            _same_frame(frame, ref[by_time[round(frame.timestamp, 6)]])
        _same_frame(ds[0], ref[by_time[round(frames[0].timestamp, 6)]])  # passed: read again from the file
    finally:
        ds.close()
    kept = FolderDataset(FolderConfig(path=str(tmp_path / "rec")))
    assert len(kept) == len(frames)
    for i, frame in enumerate(frames):
        got = kept[i]
        assert got.timestamp == pytest.approx(frame.timestamp, abs=TIMESTAMP_ROUNDING)
        np.testing.assert_array_equal(np.asarray(got.rgb), np.asarray(frame.rgb))
        np.testing.assert_allclose(got.depth, frame.depth, atol=DEPTH_ROUNDING, rtol=0)


def test_record_refuses_a_folder_holding_a_recording(recording, tmp_path):
    cfg = RealSenseConfig(path=str(recording), record=str(tmp_path / "rec"))
    ds = RealSenseDataset(cfg)
    ds[0]
    ds.close()
    with pytest.raises(DataError, match=r"already holds a recording \(expected a new or empty folder\)"):
        RealSenseDataset(cfg)


def test_a_live_camera_runs_in_real_time_with_drops_unless_told():
    """Composing the config opens no camera: dataset=realsense without a path is live."""
    cfg, _ = compose_run(["dataset=realsense"])
    assert cfg.dataset.live() and cfg.mode is Mode.realtime and cfg.realtime.drop_frames
    cfg, _ = compose_run(["dataset=realsense", "mode=sequential", "realtime.drop_frames=false"])
    assert cfg.mode is Mode.sequential and not cfg.realtime.drop_frames
    cfg, _ = compose_run(["dataset=realsense", "dataset.path=x.db3"])
    assert not cfg.dataset.live() and cfg.mode is Mode.sequential and not cfg.realtime.drop_frames


def test_start_and_stride_select_a_live_sources_frames(recording):
    """At the recorded pace, start=1 stride=2: the run's frame k is the source's frame 1 + 2k,
    arriving when it did; passes other than 1 are refused for a live source."""
    ds = RealSenseDataset(RealSenseConfig(path=str(recording), recorded_pace=True, start=1, stride=2))
    try:
        frames = []
        with pytest.raises(SourceEnded):
            while True:
                frames.append(ds[len(frames)])
        assert 1 <= len(frames) <= N // 2
        for k, frame in enumerate(frames):
            assert frame.timestamp == ds.timestamps[1 + 2 * k] and ds.arrival(k) == ds.arrivals[1 + 2 * k]
    finally:
        ds.close()
    with pytest.raises(ConfigError, match=r"dataset.passes: expected 1 for a live source"):
        RealSenseDataset(RealSenseConfig(path=str(recording), recorded_pace=True, passes=2))


def test_device_enumeration_and_the_missing_camera_line():
    """This machine has no RealSense camera: the enumeration is empty and opening one says so."""
    if sdk.list_devices():
        pytest.skip("a RealSense camera is connected here")
    with pytest.raises(DataError) as info:
        RealSenseDataset(RealSenseConfig())
    line = str(info.value)
    assert line.startswith("no RealSense camera connected (expected a D400-series camera") and "\n" not in line


def test_a_library_that_cannot_query_usb_is_one_line(monkeypatch):
    """The library's own failure to enumerate (USB permissions) is one line naming what to fix."""
    class Context:
        def query_devices(self):
            raise RuntimeError("failed to open usb interface: 0, error: RS2_USB_STATUS_ACCESS\nmore")

    monkeypatch.setattr(sdk.sdk(), "context", Context)
    with pytest.raises(DataError) as info:
        RealSenseDataset(RealSenseConfig())
    line = str(info.value)
    assert line.startswith("cannot list RealSense cameras: failed to open usb interface") and "udev rules" in line
    assert "\n" not in line


def test_the_missing_library_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as where it is not installed
    with pytest.raises(DataError) as info:
        RealSenseDataset(RealSenseConfig())
    line = str(info.value)
    assert "needs Intel's RealSense library, which is not installed" in line and sdk.REQUIREMENT in line
    assert "\n" not in line


@pytest.mark.parametrize("name, content, message", [
    ("absent.db3", None, "not found (expected a .bag or .db3 file"),
    ("frames.mp4", b"x", "a .mp4 file (expected .bag or .db3)"),
    ("broken.db3", b"not an sqlite file" * 100, "cannot"),
    ("broken.bag", b"#ROSBAG V2.0\n" + b"\0" * 64, "cannot"),
    ("empty.bag", b"", "cannot"),
])
def test_bad_recordings_fail_in_one_line(tmp_path, name, content, message):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(DataError) as info:
        RealSenseDataset(RealSenseConfig(path=str(path)))
    line = str(info.value)
    assert message in line and str(path) in line and "\n" not in line


@pytest.mark.parametrize("name, message", [
    ("frames.db3", "a RealSense ROS1 recording is a .bag file (expected a name ending in .bag)"),
    ("absent/frames.bag", "cannot write a RealSense .bag here"),
])
def test_a_bag_is_written_only_to_a_new_bag_file(tmp_path, name, message):
    with pytest.raises(DataError) as info:
        write_bag_recording(_tum(), tmp_path / name)
    line = str(info.value)
    assert message in line and str(tmp_path / name) in line and "\n" not in line
