"""A live RealSense source's capture: a thread that takes every frame set a camera (or a recording
at its recorded pace) gives, as it comes, numbers them in order (the raw frames) and keeps those
the run takes (`start`, `stride`) until the run asks for them."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from slamkit.errors import DataError
from slamkit.roles import SourceEnded
from slamkit_plugins.datasets.realsense.recording import TumRecorder
from slamkit_plugins.datasets.realsense.stream import FrameSet, Stream

log = logging.getLogger(__name__)


class LiveCapture:
    """The capture thread of `stream`, started here; it waits for the run's first `take` (a
    recording's playback starts then).

    file_stamps: a recording's colour timestamps (seconds), to count the frame sets its playback
    skipped; None for a camera (its frame counter's gaps are counted). limit: raw frame sets to
    take at most. start, stride, queue, timeout_s: as `RealSenseConfig`. recorder: where the
    taken frame sets are kept, or None."""

    def __init__(self, stream: Stream, file_stamps: list[float] | None, limit: int, start: int, stride: int,
                 queue: int, timeout_s: float, recorder: TumRecorder | None):
        self.stream, self.file_stamps, self.limit = stream, file_stamps, limit
        self.start, self.stride, self.queue, self.timeout_s, self.recorder = start, stride, queue, timeout_s, recorder
        self.timestamps: list[float] = []  # of every raw frame set taken from the source
        self.arrivals: list[float] = []  # time.perf_counter() of each
        self.source_dropped = 0  # frame sets the camera or the queue dropped before the run saw them
        self._frames: dict[int, FrameSet] = {}
        self._taken = threading.Condition(threading.RLock())
        self._error: DataError | None = None
        self._ended = False
        self._running = True
        self._asked = threading.Event()  # the run has asked for its first frame
        self._thread = threading.Thread(target=self._capture_all, name="slamkit-realsense", daemon=True)
        self._thread.start()

    def arrival(self, raw: int) -> float | None:
        """time.perf_counter() seconds when raw frame set `raw` came (None: not yet)."""
        arrivals = self.arrivals
        return arrivals[raw] if raw < len(arrivals) else None

    def take(self, raw: int) -> FrameSet | None:
        """Raw frame set `raw`: waits for it (DataError after timeout_s); None when it came and
        the run has passed it (taken before, or not kept); SourceEnded past the source's end."""
        self._asked.set()
        deadline = time.monotonic() + self.timeout_s
        with self._taken:
            while raw not in self._frames and raw >= len(self.arrivals):
                if self._error is not None:
                    raise self._error
                if self._ended:
                    raise SourceEnded(f"{self.stream.where} ended after {len(self.arrivals)} frames")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DataError(f"{self.stream.where} gave no frame in {self.timeout_s:g} s (expected one every "
                                    f"1/{self.stream.fps} s; is it still connected? dataset.timeout_s waits longer)")
                self._taken.wait(left)
            return self._frames.pop(raw, None)

    def stop(self) -> None:
        """End the capture at its next frame set (the stream itself is stopped by its owner)."""
        self._running = False

    def _capture_all(self) -> None:
        """Every frame set the source gives, from the run's first request on, numbered in order,
        until `limit` or `stop`; those the queue has no room for, and those the source skipped,
        counted in `source_dropped`."""
        last_number = None
        try:
            while not self._asked.wait(0.1):  # from the run's first frame on, as it is ready for them
                if not self._running:
                    return
            self.stream.resume()
            while self._running and len(self.arrivals) < self.limit:
                frames = self.stream.next(self.timeout_s)
                arrival = time.perf_counter()
                if frames is None:  # a recording's end
                    break
                if self.file_stamps is not None:  # a recording: its frame sets before this one that did not come
                    number = int(np.searchsorted(self.file_stamps, frames.timestamp - 1e-7))
                    last_number = -1 if last_number is None else last_number
                else:  # a camera: the gaps in its frame counter
                    number = frames.number
                if last_number is not None and number > last_number + 1:
                    self._dropped_at_source(number - last_number - 1, "the camera, the USB link or the playback")
                last_number = number
                with self._taken:
                    index = len(self.arrivals)
                    taken = index >= self.start and (index - self.start) % self.stride == 0
                    if taken and len(self._frames) >= self.queue:
                        self._dropped_at_source(1, f"the run's queue of {self.queue} frames being full")
                        continue
                    if taken:
                        self._frames[index] = frames
                    self.timestamps.append(frames.timestamp)
                    self.arrivals.append(arrival)
                    self._taken.notify_all()
                if taken and self.recorder is not None:
                    self.recorder.add(index, frames.timestamp, frames.rgb, frames.depth_raw)
        except DataError as exc:
            with self._taken:
                self._error = exc
                self._taken.notify_all()
        finally:
            self.stream.stop()
            with self._taken:
                self._ended = True
                self._taken.notify_all()

    def _dropped_at_source(self, n: int, why: str) -> None:
        self.source_dropped += n
        log.warning("%s: %d frame(s) dropped before the run saw them (%s; %d so far)", self.stream.where, n, why,
                    self.source_dropped)
