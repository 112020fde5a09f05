"""A RealSense recording played frame by frame through its own sensors (`RecordingPlayback`),
every frame set given once and in order: what `Stream` plays a recording with unless it is
asked for the recorded pace."""

from __future__ import annotations

import atexit
import collections
import queue
import threading
import time
import weakref
from pathlib import Path

from slamkit.errors import DataError
from slamkit_plugins.datasets.realsense.sdk import first_line, no_frame

#: Milliseconds between two looks at a recording's playback status while waiting for its next frame set.
POLL_MS = 100
#: Milliseconds a recording played frame by frame is waited on once it has ended (its end is
#: signalled after its last frames are handed over: one more look).
FILE_END_MS = POLL_MS
#: Frames held between a recording's playback and the reader (the playback waits while it is full).
FILE_QUEUE = 8
#: Seconds of one stream's frames held at the most while waiting for the other's of their time.
HELD_S = 2.0

# The playbacks not stopped yet: stopped at the interpreter's exit, before the SDK's own teardown,
# which aborts the process when it meets a playback device still playing ("FATAL: exception not
# rethrown"); a user who never calls `Stream.stop` loses nothing for it.
_PLAYING: weakref.WeakSet = weakref.WeakSet()
_PLAYING_LOCK = threading.Lock()  # a reader's thread may start or stop one while the exit looks


@atexit.register
def _stop_playing() -> None:
    with _PLAYING_LOCK:
        playing = list(_PLAYING)
    for playback in playing:
        playback.stop()


class RecordingPlayback:
    """A recording played frame by frame through its own sensors, without a pipeline: made
    non-real-time and paused before any frame is played, every stream's frames queued as played
    (in order within a stream; the playback waits while the queue is full), and a colour frame
    paired here with the depth frame of its time, so that every pass gives every frame set (the
    pipeline starts a recording in real time and must seek back to its start, and now and then
    lost the first frame set doing so: docs/datasets.md). One queue for all the streams,
    not one each: the SDK reads the file on one thread, in time order, so a stream that runs
    ahead (colour starting late, a gap in one stream) must not fill a queue the reader is not
    emptying. `profiles`: the (colour, depth) stream profiles; `device`: the playback device."""

    def __init__(self, rs, path: Path, where: str):
        self.rs, self.where = rs, where
        self.sensors: list = []  # those started: stopped by `stop`
        self.stopping = threading.Event()
        with _PLAYING_LOCK:
            _PLAYING.add(self)
        try:
            self.context = rs.context()
            self.device = self.context.load_device(str(path))
            self.playback = self.device.as_playback()
            self.playback.set_real_time(False)
            self._start(rs)
        except RuntimeError as exc:
            self.stop()
            raise DataError(f"cannot play {where}: {first_line(exc)} (expected a .bag or .db3 recording the "
                            "RealSense SDK wrote)") from None
        except DataError:
            self.stop()
            raise

    def _start(self, rs) -> None:
        wanted = (rs.stream.color, rs.stream.depth)
        sensors = list(self.device.query_sensors())
        chosen: dict = {}  # stream kind -> (its sensor's index, its profile): the first of each kind
        kinds = []
        for i, sensor in enumerate(sensors):
            for profile in sensor.get_stream_profiles():
                kinds.append(str(profile.stream_type()).split(".")[-1])
                if profile.stream_type() in wanted and profile.stream_type() not in chosen:
                    chosen[profile.stream_type()] = (i, profile)
        if len(chosen) < len(wanted):
            raise DataError(f"{self.where} has no colour and depth stream pair (it has: {', '.join(kinds) or 'none'}; "
                            "expected both)")
        self.profiles = tuple(chosen[kind][1].as_video_stream_profile() for kind in wanted)
        rates = [p.fps() for p in self.profiles]
        if min(rates) <= 0:
            raise DataError(f"{self.where}: colour and depth at {rates[0]} and {rates[1]} frames/s (expected both > 0)")
        self.fps = rates[0]
        # colour and depth within half the faster stream's period are one frame set: at most one
        # frame of the faster stream is that near a frame of the other
        self.tolerance_ms = 500.0 / max(rates)
        self.played: queue.Queue = queue.Queue(FILE_QUEUE)  # every stream's frames, in the order played
        # frames taken from `played` and not paired yet, by stream kind: a frame of one stream
        # waits for the other's of its time (held HELD_S at the most: the file is read in time order)
        self.held = {kind: collections.deque(maxlen=max(1, int(HELD_S * rate))) for kind, rate in zip(wanted, rates)}
        # paused while the sensors start one after the other: a frame played before its sensor
        # has started is lost (a .bag's first colour frame, now and then, unpaused)
        self.playback.pause()
        for sensor in [sensors[i] for i in sorted({i for i, _ in chosen.values()})]:
            sensor.open([p for i, p in chosen.values() if sensors[i] is sensor])
            self.sensors.append(sensor)
            sensor.start(self._queued)
        self.playback.resume()  # (its status now reads "playing" until the file's end)
        # a (colour, depth) pair the SDK did not pair itself, as the frame set `rs.align` takes
        self._depth: list = []
        self._composer = rs.processing_block(
            lambda frame, source: source.frame_ready(source.allocate_composite_frame([frame, *self._depth])))
        self._composed = rs.frame_queue(1)
        self._composer.start(self._composed)

    def _queued(self, frame) -> None:
        """The sensors' callback (the SDK's thread of each stream): the frame into `played`, waiting
        while it is full."""
        frame.keep()
        while not self.stopping.is_set():
            try:
                self.played.put(frame, timeout=POLL_MS / 1000)
                return
            except queue.Full:
                pass

    def next(self, timeout_s: float):
        """The next (colour, depth) frames of one time; None at the recording's end. A frame whose
        other half was never recorded (none within `tolerance_ms`) is passed over."""
        colors, depths = self.held[self.rs.stream.color], self.held[self.rs.stream.depth]
        while True:
            while colors and depths:
                tc, td = colors[0].get_timestamp(), depths[0].get_timestamp()
                if abs(tc - td) <= self.tolerance_ms:
                    return colors.popleft(), depths.popleft()
                (colors if tc < td else depths).popleft()
            frame = self._take(timeout_s)
            if frame is None:
                return None
            self.held[frame.get_profile().stream_type()].append(frame)

    def _take(self, timeout_s: float):
        """The next frame played: None once the playback has stopped at the file's end and no
        frame came for FILE_END_MS; DataError when none came within `timeout_s` while it played."""
        deadline, ended = time.monotonic() + timeout_s, None
        while True:
            playback = self.playback
            if self.stopping.is_set() or playback is None:  # stopped by another thread (the run's end)
                raise DataError(f"{self.where} was closed while a frame was being read")
            try:
                return self.played.get(timeout=POLL_MS / 1000)
            except queue.Empty:
                pass
            now = time.monotonic()
            if playback.current_status() == self.rs.playback_status.stopped:
                ended = ended or now + FILE_END_MS / 1000  # the last frames may still be on their way
                if now > ended:
                    return None
            elif now > deadline:
                raise no_frame(self.where, timeout_s, self.fps, True)

    def frame_set(self, color, depth):
        """`color` and `depth` as one frame set (what `rs.align` takes)."""
        composer, composed = self._composer, self._composed
        if composer is None or composed is None:
            raise DataError(f"{self.where} was closed while a frame was being read")
        self._depth[:] = [depth]
        composer.invoke(color)
        return composed.wait_for_frame().as_frameset()

    def stop(self) -> None:
        """Stop the sensors and let the playback go now (at the interpreter's exit at the latest:
        `_stop_playing`); again is a no-op."""
        self.stopping.set()  # a callback waiting on a full queue returns
        with _PLAYING_LOCK:
            _PLAYING.discard(self)
        for sensor in self.sensors:
            for step in (sensor.stop, sensor.close):
                try:
                    step()
                except RuntimeError:
                    pass
        played = getattr(self, "played", None)  # the frames kept for the reader go now (`held`'s: with it)
        while played is not None:
            try:
                played.get_nowait()
            except queue.Empty:  # (a read on another thread may take the last one first)
                break
        getattr(self, "_depth", []).clear()
        self.sensors, self.profiles, self._composer, self._composed = [], (), None, None
        self.device = self.playback = self.context = None
