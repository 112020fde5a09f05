"""How a run feeds frames to its `SLAM`: `Runner` (sequential mode) calls `SLAM.process` on each
frame as it is read; `RealtimeRunner` makes the same call on each frame at its time on an input
clock (`InputClock` at `realtime.fps_limit`, or a live source's own, `slamkit.run.live.LiveClock`) while
its workers (`slamkit.run.workers`) train the map and decide on loops beside tracking, the
mapping worker at a lower priority and out of the way of a late frame (`realtime.mapping_yields`), and
the mapper takes each keyframe beside tracking (`SLAM.handovers`, built by `slamkit.run.build`).
There is one per-frame path, the SLAM's; a runner adds only when a frame is taken and what runs
beside it.

The pipeline (`slamkit.run.pipeline.Pipeline`) drives a runner: `start`, then for each frame
`wait`, `arrival`, `process`, `frame_done`, then `stop` (whatever ended the stream).
"""

from __future__ import annotations

import time

from slamkit.run.live import LiveClock
from slamkit.run.slam import SLAM, StepResult
from slamkit.run.state import RunState
from slamkit.run.workers import LoopThread, MappingThread
from slamkit.scheduling import ThreadPriority
from slamkit.types import Frame


class InputClock:
    """Paces input like a live camera: frame i arrives `i / fps` seconds after the first."""

    def __init__(self, fps: float | None):
        self.period = 1.0 / fps if fps else 0.0
        self.start: float | None = None

    def late_after(self, i: int) -> float | None:
        """When tracking frame i, started now, is late (time.perf_counter() seconds): once frame
        i+1 has arrived, or one period from now when that was already so (a tracker behind its
        input is late only on a frame slower than the input rate); None without an input rate or
        before frame 0 has arrived."""
        if not self.period or self.start is None:
            return None
        return max(self.start + (i + 1) * self.period, time.perf_counter() + self.period)

    def arrival(self, i: int) -> float | None:
        """When frame i arrived (time.perf_counter() seconds); None without an input rate."""
        return self.start + i * self.period if self.period and self.start is not None else None

    def wait(self, i: int) -> bool:
        """Sleep until frame i has arrived; True if frame i+1 has arrived too (we are late)."""
        if not self.period:
            return False
        now = time.perf_counter()
        if self.start is None:
            self.start = now
        arrival = self.start + i * self.period
        if now < arrival:
            time.sleep(arrival - now)
            return False
        return now >= arrival + self.period


class Runner:
    """Sequential mode: each frame is processed when the stream reads it, the mapping steps and
    the loop closure's decision inside `SLAM.process` (no input rate, no worker)."""

    def __init__(self, slam: SLAM, clock: InputClock | LiveClock | None = None):
        self.slam = slam
        self.clock = clock or InputClock(None)

    def start(self) -> None:
        """Start what runs beside the stream (nothing here)."""

    def wait(self, i: int) -> bool:
        """Until the stream's frame i has arrived; True if frame i+1 has arrived too (late)."""
        return self.clock.wait(i)

    def arrival(self, i: int) -> float:
        """When the stream's frame i arrived (time.perf_counter() seconds): at its time on the
        input clock, else now (when the stream takes it)."""
        return self.clock.arrival(i) or time.perf_counter()

    def process(self, frame: Frame, i: int) -> StepResult:
        """`SLAM.process(frame)`, the stream's frame i."""
        return self.slam.process(frame)

    def frame_done(self) -> None:
        """The tracking thread is done with the frame (its row written, shown)."""

    def settle(self, state: RunState) -> BaseException | None:
        """Wait for the keyframe going to the mapper beside tracking and count the stream's
        handovers into `state` (the run's SLAM streams once); its failure is returned, to be
        raised once the stream's threads are stopped."""
        try:
            self.slam.settle()
        except BaseException as exc:  # noqa: BLE001 - raised by the caller after its cleanup
            return exc
        finally:
            if self.slam.handovers is not None:
                state.keyframe_handover_s += self.slam.handovers.time_s
                state.keyframe_handover_wait_s += self.slam.handovers.wait_s
        return None

    def stop(self, state: RunState) -> None:
        """Stop what ran beside the stream and count its work into `state` (nothing here)."""


class RealtimeRunner(Runner):
    """Real time: frames taken at their time on `clock` (`InputClock` at `realtime.fps_limit`, None: as
    fast as tracking goes; a live source's `LiveClock`), a `MappingThread` training the map at
    `realtime.mapping_priority` (Python's switch interval `switch_interval_s` while it runs) that starts
    no step while tracking is late on a frame (`realtime.mapping_yields`), and a `LoopThread` for a loop
    closure that closes loops. The SLAM must be built for it (`beside=True`: its `process`
    neither trains nor detects)."""

    def __init__(self, slam: SLAM, clock: InputClock | LiveClock, switch_interval_s: float,
                 mapping_priority: ThreadPriority, mapping_yields: bool):
        if not slam.beside:
            raise ValueError("RealtimeRunner: the SLAM must be built with beside=True (its workers train and detect)")
        super().__init__(slam, clock)
        self.mapping = MappingThread(slam, switch_interval_s, mapping_priority)
        self.loops = LoopThread(slam.loop_closer) if slam.loop_closer.active else None
        self.mapping_yields = mapping_yields

    def start(self) -> None:
        self.mapping.start()
        if self.loops:
            self.loops.start()

    def process(self, frame: Frame, i: int) -> StepResult:
        """`SLAM.process(frame)` with no mapping step starting once it is late (`realtime.mapping_yields`);
        a worker's failure is raised here, on the tracking thread."""
        if self.mapping_yields:
            self.mapping.yield_to_tracking(self.clock.late_after(i))
        step = self.slam.process(frame)
        self.mapping.check()
        if self.loops:
            self.loops.check()
        return step

    def frame_done(self) -> None:
        self.mapping.yield_to_tracking(None)

    def stop(self, state: RunState) -> None:
        """Mapping first: a loop closure's call in progress then has the CPUs to end."""
        try:
            self._stop_mapping(state)
        finally:
            if self.loops:
                self.loops.stop()

    def _stop_mapping(self, state: RunState) -> None:
        mapping = self.mapping
        try:
            mapping.stop()
        finally:
            state.mapping_iterations += mapping.iterations
            state.mapping_time_s += mapping.busy_time_s
            state.mapping_cpu_s = (state.mapping_cpu_s or 0.0) + mapping.cpu_time_s
            state.mapping_throttle = mapping.throttle


__all__ = ["InputClock", "RealtimeRunner", "Runner"]
