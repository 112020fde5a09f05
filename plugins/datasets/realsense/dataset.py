"""The `realsense` dataset: a RealSense camera live, or a RealSense recording (.bag, .db3)."""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import sys
import tempfile
import threading
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.formats.tum import interpolate_poses, read_tum_trajectory
from slamkit.roles import Dataset, DatasetConfig, DatasetTuning, RunContext, require
from slamkit.types import Camera, Frame
from slamkit_plugins.datasets.realsense.capture import LiveCapture
from slamkit_plugins.datasets.realsense.recording import TumRecorder
from slamkit_plugins.datasets.realsense.sdk import RECORDING_SUFFIXES
from slamkit_plugins.datasets.realsense.stream import FrameSet, Stream

log = logging.getLogger(__name__)

#: The raw frames of a live source: without dataset.max_frames it ends on a signal (Ctrl-C).
LIVE_FRAMES = sys.maxsize
#: Seconds: a frame set read again has the timestamp it had at start-up (the same file), to this.
SAME_STAMP_S = 1e-6
#: Plays from the start again, at most, when the SDK skipped a frame set, before a DataError.
MAX_RESTARTS = 3


@dataclass
class RealSenseConfig(DatasetConfig):
    """Options of a RealSense source (`path`: a .bag or .db3 recording; empty: the camera, live)."""

    #: a .bag or .db3 RealSense recording (empty: the camera, live)
    path: str = ""
    #: the camera's serial number (null: the only RealSense camera connected); live only
    serial: str | None = None
    #: pixels; the colour and depth streams' width (live only; a recording has its own)
    width: int = 640
    #: pixels; the colour and depth streams' height (live only)
    height: int = 480
    #: frames per second of both streams (live only)
    fps: int = 30
    #: depth reprojected into the colour camera by the SDK (false: depth must already be the colour camera's)
    align: bool = True
    #: keep the frames in this folder in the TUM layout, to replay and evaluate later (null: not kept)
    record: str | None = None
    #: a recording: played at its recorded pace, as the camera gave it (frames the run is busy for are dropped)
    recorded_pace: bool = False
    #: seconds to wait for the camera's next frame before the run stops with an error
    timeout_s: float = 5.0
    #: live: frames held between the camera and the run; when full, new ones are dropped at the source (counted)
    queue: int = 60
    #: TUM-format ground truth (camera-to-world, metres), interpolated at the colour timestamps (null: none)
    groundtruth: str | None = None
    #: seconds between a colour timestamp and the nearest ground-truth pose
    gt_tolerance: float = 0.02

    def validate(self) -> None:
        super().validate()
        require(self.width > 0 and self.height > 0, "dataset.width / dataset.height", "positive pixels",
                (self.width, self.height))
        require(self.fps > 0, "dataset.fps", "> 0 frames per second", self.fps)
        require(self.timeout_s > 0, "dataset.timeout_s", "> 0 seconds", self.timeout_s)
        require(self.queue >= 1, "dataset.queue", "an integer >= 1 frames", self.queue)
        require(self.gt_tolerance > 0, "dataset.gt_tolerance", "> 0 seconds", self.gt_tolerance)

    def live(self) -> bool:
        """A camera, or a recording at its recorded pace: frames come whether the run is ready or not."""
        return not self.path or self.recorded_pace


class RealSenseDataset(Dataset):
    """Frames of a RealSense camera or recording (see RealSenseConfig). Timestamps are the colour
    frames' device times (seconds); depth in metres (raw units times the device's depth scale),
    in the colour camera's pixels; gt_pose camera-to-world from `groundtruth` or None.

    A recording is read one frame set at a time in order (reading an earlier frame again plays
    it from the start), after one pass at start-up that counts its frames. A live source (a
    camera, or a recording at its recorded pace) is read by a thread of its own as frame sets
    come (`arrival`); frame i waits for the i-th, and one the run has passed is read again from
    the recording file, else from `record` (a camera's are kept in a temporary folder when the
    run has max_frames, for its evaluation), else is gone."""

    #: a hand-held D400 indoors: its stereo depth error grows with the square of the distance, so
    #: tracking uses depth within 3 m (as TUM's Kinect); the generic profile otherwise
    default_tuning = DatasetTuning(depth_trunc=3.0)

    def __init__(self, cfg: RealSenseConfig, context: RunContext = RunContext()):
        super().__init__(cfg)
        require(not cfg.live() or cfg.passes == 1, "dataset.passes", "1 for a live source (a camera, or a "
                "recording at its recorded_pace)", cfg.passes)
        self._lock = threading.RLock()
        self.path = None if not cfg.path else self._recording(cfg.path)
        self.file_stamps: list[float] = []  # a recording: the colour timestamp of each of its frame sets
        self._last: float | None = None  # the colour timestamp (s) of the frame set `reader` gave last
        self._streams: list[Stream] = []  # every stream opened: stopped by `close`, or at exit
        weakref.finalize(self, _stop, self._streams)
        if self.path is None:
            self.stream = self._open(None, cfg.serial, cfg.width, cfg.height, cfg.fps, cfg.align)
        else:
            self.stream = self._open(self.path, align=cfg.align)
            self._index_recording()
        self.reader = self.stream if not cfg.recorded_pace else None  # the recording read frame set by frame set
        if cfg.recorded_pace:
            self.stream.stop()
            self.stream = self._open(self.path, align=cfg.align, real_time=True)
        self.where = self.stream.where
        self._camera = self.stream.camera
        self.units_per_metre = 1.0 / self.stream.depth_scale
        self.default_tuning = dataclasses.replace(self.default_tuning, depth_scale=self.units_per_metre)
        log.info("%s: %dx%d at %d frames/s, depth scale %.6g m, depth %s", self.where, self._camera.width,
                 self._camera.height, self.stream.fps, self.stream.depth_scale,
                 "aligned to colour by the SDK" if self.stream.aligned else "already in the colour camera")
        self.gt = self._ground_truth()
        self.recorder = self._recorder()
        self.capture: LiveCapture | None = None  # a live source's frames, taken as they come
        if cfg.live():
            self.capture = LiveCapture(
                self.stream, None if self.path is None else self.file_stamps,
                LIVE_FRAMES if cfg.max_frames is None else self.raw_indices()[-1] + 1,
                cfg.start, cfg.stride, cfg.queue, cfg.timeout_s, self.recorder)

    # -- set-up ---------------------------------------------------------------------------------
    @staticmethod
    def _recording(name: str) -> Path:
        path = Path(os.path.expanduser(name))
        if not path.is_file():
            raise DataError(f"RealSense recording {path} not found (expected a {' or '.join(RECORDING_SUFFIXES)} "
                            "file the RealSense SDK recorded)")
        if path.suffix.lower() not in RECORDING_SUFFIXES:
            raise DataError(f"RealSense recording {path}: a {path.suffix or 'suffix-less'} file (expected "
                            f"{' or '.join(RECORDING_SUFFIXES)})")
        return path

    def _recorder(self) -> TumRecorder | None:
        cfg = self.cfg
        if cfg.record is not None:
            root = Path(os.path.expanduser(cfg.record))
        elif self.path is None and cfg.max_frames is not None:  # the evaluation reads the frames again
            root = Path(tempfile.mkdtemp(prefix="slamkit-realsense-"))
            weakref.finalize(self, shutil.rmtree, root, True)
        else:
            return None
        recorder = TumRecorder(root, self._camera, self.units_per_metre)
        weakref.finalize(self, recorder.close)  # at exit too: the frames queued are written
        return recorder

    def _index_recording(self) -> None:
        """One pass over the recording: its frame sets' timestamps; then back to its start."""
        while (frames := self.stream.next(self.cfg.timeout_s)) is not None:
            self.file_stamps.append(frames.timestamp)
        if not self.file_stamps:
            raise DataError(f"{self.stream.where} has no frame with both colour and depth (expected a recording of a "
                            "colour and a depth stream)")
        back = np.flatnonzero(np.diff(self.file_stamps) <= 0)
        if len(back):  # frame sets are found by their timestamps (the SDK can skip one on any pass)
            k = int(back[0]) + 1
            raise DataError(f"{self.stream.where}: frame set {k}'s colour timestamp {self.file_stamps[k]:.6f} s is not "
                            f"after frame set {k - 1}'s {self.file_stamps[k - 1]:.6f} s (expected a recording whose "
                            "device times increase)")
        self.stream = self._restarted(self.stream)
        # should a pass lose its first frame set (the SDK's pipeline did, CI saw a .bag's go): the second
        # one's first frame set read now, kept where the first pass had not seen it
        first = self.stream.next(self.cfg.timeout_s)
        if first is not None:
            self._last = first.timestamp
            if first.timestamp < self.file_stamps[0] - SAME_STAMP_S:
                self.file_stamps.insert(0, first.timestamp)

    def _open(self, *args, **kwargs) -> Stream:
        stream = Stream(*args, **kwargs)
        self._streams[:] = [s for s in self._streams if s.running] + [stream]
        return stream

    def _restarted(self, stream: Stream) -> Stream:
        """`stream` played again from the recording's start, frame set by frame set."""
        stream.stop()
        self._last = None
        return self._open(self.path, align=self.cfg.align)

    def _ground_truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(timestamps in seconds, (N,4,4) camera-to-world poses) of `groundtruth`, or None."""
        if self.cfg.groundtruth is None:
            return None
        path = Path(os.path.expanduser(self.cfg.groundtruth))
        if not path.is_file():
            raise DataError(f"dataset.groundtruth: {path} not found (expected a TUM-format trajectory file)")
        if self.path is None:
            raise DataError("dataset.groundtruth: a live camera has none (expected it with dataset.path, a recording)")
        gt_ts, gt = read_tum_trajectory(path)
        stamps = np.asarray(self.file_stamps)
        if not np.isfinite(interpolate_poses(gt_ts, gt, stamps, self.cfg.gt_tolerance)).all(axis=(1, 2)).any():
            raise DataError(f"{path}: no pose within {self.cfg.gt_tolerance} s of any colour timestamp "
                            f"({stamps[0]:.6f} .. {stamps[-1]:.6f}; expected the recording's time)")
        return gt_ts, gt

    # -- live capture ---------------------------------------------------------------------------
    @property
    def timestamps(self) -> list[float]:
        """Seconds, of the raw frames: a live source's as they came, else the recording's."""
        return self.file_stamps if self.capture is None else self.capture.timestamps

    @property
    def arrivals(self) -> list[float]:
        """Live: time.perf_counter() of each raw frame set taken from the source (else empty)."""
        return [] if self.capture is None else self.capture.arrivals

    @property
    def source_dropped(self) -> int:
        """Live: frame sets the camera or the queue dropped before the run saw them."""
        return 0 if self.capture is None else self.capture.source_dropped

    def close(self) -> None:
        """Stop the camera or the playback and finish the recording; again is a no-op."""
        if self.capture is not None:
            self.capture.stop()
        _stop(self._streams)
        if self.recorder is not None:
            self.recorder.close()

    @property
    def live(self) -> bool:
        return self.cfg.live()

    def arrival(self, i: int) -> float | None:
        """Live: time.perf_counter() seconds when frame i of the run (raw frame start + i * stride)
        was taken from the camera (None: not yet). A recording: None (the run paces it, `realtime.fps_limit`)."""
        return None if self.capture is None else self.capture.arrival(self.cfg.start + i * self.cfg.stride)

    # -- the Dataset role -------------------------------------------------------------------------
    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return LIVE_FRAMES if self.cfg.live() else len(self.file_stamps)

    def raw_timestamp(self, raw_index: int) -> float:
        stamps = self.timestamps
        return float(stamps[raw_index]) if raw_index < len(stamps) else raw_index / float(self.stream.fps)

    def load(self, raw_index: int) -> Frame:
        frames = self._live(raw_index) if self.cfg.live() else self._played(raw_index)
        if frames is None:  # passed: from the recording folder
            rgb, depth = self.recorder.read(raw_index)
        else:
            depth = frames.depth_raw.astype(np.float32)  # metres = raw / units per metre, as every 16-bit depth
            rgb, depth = frames.rgb, np.divide(depth, np.float32(self.units_per_metre), out=depth)
        timestamp = float(self.timestamps[raw_index])
        gt = None
        if self.gt is not None:
            pose = interpolate_poses(*self.gt, np.array([timestamp]), self.cfg.gt_tolerance)[0]
            gt = pose if np.isfinite(pose).all() else None
        return Frame(raw_index, timestamp, rgb, depth, self._camera, gt)

    def _played(self, k: int) -> FrameSet | None:
        """Frame set k of the recording file (None: it is in `record` already)."""
        stamp = self.file_stamps[k]
        with self._lock:
            if self._passed(stamp) and not self.cfg.live() and self.recorder is not None and k in self.recorder.files:
                return None
            frames = self._played_at(stamp, f"frame set {k}")
        if self.recorder is not None and not self.cfg.live():
            self.recorder.add(k, frames.timestamp, frames.rgb, frames.depth_raw)
        return frames

    def _passed(self, stamp: float) -> bool:
        """Whether the reader has given the frame set of colour timestamp `stamp` (s) already."""
        return self._last is not None and stamp <= self._last + SAME_STAMP_S

    def _played_at(self, stamp: float, name: str) -> FrameSet:
        """The recording's frame set of colour timestamp `stamp` (seconds), read on from where the
        reader is, or from the recording's start once passed. The frame sets before it are passed
        over, those the start-up pass never saw too: the SDK's playback can skip one on any pass."""
        with self._lock:
            if self.reader is None:  # a recording at its pace, read again: frame by frame from here on
                self.reader = self._open(self.path, align=self.cfg.align)
                self._last = None
            if self._passed(stamp):
                self.reader = self._restarted(self.reader)
            restarts = 0
            while True:
                frames = self.reader.next(self.cfg.timeout_s)
                if frames is None:
                    raise DataError(f"{self.where} ended before {name} ({stamp:.6f} s) of the {len(self.file_stamps)} "
                                    "it had at start-up (expected the same frames on every pass)")
                self._last = frames.timestamp
                if frames.timestamp < stamp - SAME_STAMP_S:
                    continue
                if frames.timestamp <= stamp + SAME_STAMP_S:
                    return frames
                # the SDK skipped this frame set (its pipeline's playback did on a busy machine): the
                # next one must not stand in for it; played again from the start
                restarts += 1
                if restarts > MAX_RESTARTS:
                    raise DataError(f"{self.where}: {name} came with timestamp {frames.timestamp:.6f} s, expected "
                                    f"{stamp:.6f} s (the SDK skipped frame sets on {MAX_RESTARTS + 1} passes)")
                self.reader = self._restarted(self.reader)

    def _live(self, i: int) -> FrameSet | None:
        """Frame set i of a live source: waits for it. One the run has passed: from the
        recording file, else None when `record` has it; SourceEnded past a recording's end."""
        frames = self.capture.take(i)
        if frames is not None:
            return frames
        if self.path is not None:  # passed: read again from the file, at the same device time
            return self._played_at(self.timestamps[i], f"frame {i}")
        if self.recorder is None:
            raise DataError(f"frame {i} of {self.where} has passed and was not kept (expected dataset.record=DIR "
                            "to read a live camera's frames again)")
        return None


def _stop(streams: list[Stream]) -> None:
    for stream in streams:
        stream.stop()
