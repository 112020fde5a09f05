"""The workers a real-time run keeps beside tracking (`slamkit.run.runner.RealtimeRunner`):
`MappingThread` trains the map (`SLAM.optimize(1)` in a loop) at a lower priority, `LoopThread`
hands the queued keyframes to the loop closure (`LoopCloser.detect`). Each is a `Worker`, which
re-raises its failure on the tracking thread (`check`, `stop`)."""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from slamkit.run.loop_closing import LoopCloser
from slamkit.scheduling import ThreadPriority, lower_calling_thread, thread_schedule

if TYPE_CHECKING:  # annotations only: the algorithm does not depend on its workers
    from slamkit.run.slam import SLAM


@dataclass
class MappingThrottle:
    """What held the real-time mapping thread back, in seconds of the stream: `cpu_wait_s`
    runnable but waiting for a CPU (threads of higher priority, tracking and reading, or other
    processes went first), `no_keyframe_s` waiting for a first keyframe to train on, `blocked_s`
    the rest of its steps' time not on a CPU (the GIL, the map's lock, the kernels' workers),
    `yielded_s` paused for a late tracker. `priority` is what it ran at ("same" where the OS
    refused a lower one)."""

    priority: str
    cpu_wait_s: float | None = None
    no_keyframe_s: float = 0.0
    blocked_s: float | None = None
    yielded_s: float = 0.0  # paused between steps while tracking was late (`MappingThread.tracking_deadline`)


#: The longest a mapping thread waits for a late tracker at a time (it is woken when tracking is
#: done with the frame, or stopped).
YIELD_WAIT_S = 0.05


class Worker(threading.Thread):
    """A daemon thread beside tracking that hands its failure to the tracking thread: `error`
    (what `run` raised), re-raised by `check()` and by `stop()`, which asks it to end (`_wake`:
    whatever it may be waiting on), joins it and undoes what its start changed (`_stopped`)."""

    def __init__(self, name: str):
        super().__init__(name=name, daemon=True)
        self.error: BaseException | None = None
        self._stop_event = threading.Event()

    def check(self) -> None:
        """Re-raise the worker's failure in the calling (tracking) thread."""
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        self._stop_event.set()
        self._wake()
        if self.is_alive():
            self.join()
        self._stopped()
        self.check()

    def _wake(self) -> None:
        """End a wait of the worker's, so that it sees the stop at once."""

    def _stopped(self) -> None:
        """After the worker has ended."""


class MappingThread(Worker):
    """Runs `slam.optimize(1)` in a loop beside tracking (real-time mode), at `priority`
    (`slamkit.scheduling`; the threads and the compiled kernels' pools it uses run at it too),
    so that the tracker and the frame reader get the CPU first and mapping takes what is left.

    The mapper changes the shared map only under `gaussian_map.lock` and the tracker reads it
    only through `tracking_target()` copies, so no copy of the whole map is made per frame.
    An exception in the mapper stops the loop and is re-raised by `check()` / `stop()`.
    While tracking is late on a frame (past `tracking_deadline`) no step starts, so that a slow
    frame has both CPUs until it is tracked (`yield_to_tracking`).
    While it runs, Python's thread switch interval is `switch_interval_s` (how long a thread
    waiting for the GIL may wait; restored by `stop()`).
    """

    def __init__(self, slam: SLAM, switch_interval_s: float, priority: ThreadPriority = ThreadPriority.idle):
        super().__init__("slamkit-mapping")
        self.slam = slam
        self.switch_interval_s = switch_interval_s
        self.priority = ThreadPriority(priority)
        self._saved_switch_interval: float | None = None
        self.iterations = 0
        self.busy_time_s = 0.0
        self.cpu_time_s = 0.0  # the thread's CPU seconds (steps, waits' overhead), when it ends
        self.throttle = MappingThrottle(self.priority.value)  # complete when it ends
        self.tracking_deadline: float | None = None  # time.perf_counter() past which tracking is late
        self._tracking_done = threading.Event()  # set while tracking is not on a frame
        self._tracking_done.set()

    def start(self) -> None:
        self._saved_switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(self.switch_interval_s)
        super().start()

    def run(self) -> None:
        lowered = lower_calling_thread(self.priority)
        schedule_start = thread_schedule()
        wall_start, cpu_start = time.perf_counter(), time.thread_time()
        try:
            while not self._stop_event.is_set():
                start = time.perf_counter()
                deadline = self.tracking_deadline
                if deadline is not None and start > deadline:  # a frame is waiting: tracking first
                    self._tracking_done.wait(YIELD_WAIT_S)
                    self.throttle.yielded_s += time.perf_counter() - start
                    continue
                done = self.slam.optimize(1)
                self.iterations += done
                if done:
                    self.busy_time_s += time.perf_counter() - start
                else:  # nothing to train on yet
                    self._stop_event.wait(0.005)
                    self.throttle.no_keyframe_s += time.perf_counter() - start
        except BaseException as exc:  # handed to the tracking thread
            self.error = exc
        finally:
            self.cpu_time_s = time.thread_time() - cpu_start
            self._account(lowered, schedule_start, time.perf_counter() - wall_start)

    def _account(self, lowered: bool, schedule_start, wall_s: float) -> None:
        throttle = self.throttle
        throttle.priority = self.priority.value if lowered else ThreadPriority.same.value
        schedule_end = thread_schedule()
        if schedule_start is not None and schedule_end is not None:
            throttle.cpu_wait_s = schedule_end.cpu_wait_s - schedule_start.cpu_wait_s
            waits = throttle.no_keyframe_s + throttle.yielded_s + throttle.cpu_wait_s
            throttle.blocked_s = max(0.0, wall_s - waits - self.cpu_time_s)

    def yield_to_tracking(self, deadline: float | None) -> None:
        """Tracking is on a frame and late past `deadline` (time.perf_counter() seconds; None:
        tracking is done with the frame, or has no input rate). Past it, no step starts."""
        self.tracking_deadline = deadline
        if deadline is None:
            self._tracking_done.set()
        else:
            self._tracking_done.clear()

    def _wake(self) -> None:
        self._tracking_done.set()

    def _stopped(self) -> None:
        if self._saved_switch_interval is not None:
            sys.setswitchinterval(self._saved_switch_interval)
            self._saved_switch_interval = None


class LoopThread(Worker):
    """Runs `closer.detect()` whenever keyframes are queued, beside tracking (real-time mode):
    tracking never waits for it, and what it decides is applied by the tracking thread between
    two frames (`LoopCloser.take`). The work itself is the loop closure's process's, at the
    mapping thread's priority (`slamkit.run.loop_process`); this thread only hands it the
    keyframes and waits for its answer, at normal priority (holding the GIL at a lower one
    while it pickles a keyframe would make tracking wait for a thread that waits for a CPU).
    It hands the keyframes over one call each, as sequential mode does, so that `stop()` (a
    stop signal) waits for one keyframe's detection at most, never for a backlog: the keyframes
    not taken stay queued (a checkpoint keeps them).
    An exception in the loop closure stops the thread and is re-raised by `check()` / `stop()`.
    `stop()` lets the call in progress end."""

    def __init__(self, closer: LoopCloser):
        super().__init__("slamkit-loop-closure")
        self.closer = closer

    def run(self) -> None:
        try:
            while not self._stop_event.is_set():
                if not self.closer.detect(limit=1):
                    self.closer.wait_for_keyframes(0.05)
        except BaseException as exc:  # handed to the tracking thread
            self.error = exc

    def _wake(self) -> None:
        self.closer.wake()
