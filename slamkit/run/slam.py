"""The SLAM loop over one shared Gaussian map, free of I/O (see `slamkit.run.pipeline` for that)."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.map.growth import MapGrowthConfig, frame_gaussians, new_gaussians
from slamkit.roles import KeyframeDecision, KeyframePolicy, Mapper, Tracker
from slamkit.run.boundary import PluginBoundary
from slamkit.run.heap import release_free_memory
from slamkit.run.loop_closing import Correction, LoopCloser
from slamkit.scheduling import ThreadPriority, lower_calling_thread, thread_schedule
from slamkit.types import Frame, KeyframeKind, TrackingResult


@dataclass
class StepResult:
    """One frame's outcome. Times in seconds. correction: the loop closure's correction applied
    after this frame was tracked (its pose is already corrected; the frames before it follow
    their keyframes: `Correction.follow`), or None."""

    tracking: TrackingResult
    decision: KeyframeDecision
    tracking_time_s: float
    mapping_time_s: float
    mapping_iterations: int
    correction: Correction | None = None

    @property
    def keyframe(self) -> KeyframeKind:
        return self.decision.kind

    def corrected(self, correction: Correction) -> StepResult:
        """This step after `correction` (its pose moved with the newest keyframe)."""
        tracking = replace(self.tracking, pose=correction.current @ self.tracking.pose)
        return replace(self, tracking=tracking,
                       correction=correction if self.correction is None else self.correction.then(correction))


class SLAM:
    """GS-ICP SLAM: a tracker and a mapper sharing one GaussianMap (sequential mode).

    Each frame is tracked against the map; a keyframe's Gaussians that the mapper admits enter
    the map (a tracking keyframe also rebuilds the tracker's target from the map, which by then
    holds the mapper's optimised values); then the mapper runs a fixed number of iterations, so
    the run is deterministic. Every keyframe goes to the loop closure (`loop_closer`); when it
    corrects the keyframes, the map's Gaussians and the mapper's keyframes move with them and the
    tracker follows (`correct`). After each keyframe the C heap's free pages go back to the OS
    (`slamkit.run.heap`), so that a long run's resident memory follows what it holds. Every call
    into a plugin passes `boundary`, which names the plugin a failure came from.

    In real time (`track(frame, defer_keyframe=True)`) the mapper takes a keyframe in a thread of
    its own (`KeyframeHandover`) while the next frames are tracked; a tracking keyframe's growth
    and the tracker's new target stay on the tracking thread, so the next frame aligns to the map
    with the keyframe in it. `handover_time_s` sums the handovers' seconds, `handover_wait_s` the
    tracking thread's waits for one (`settle`).
    """

    def __init__(self, tracker: Tracker, keyframe_policy: KeyframePolicy, mapper: Mapper, gaussian_map: GaussianMap,
                 growth: MapGrowthConfig, iterations_per_frame: int = 0, boundary: PluginBoundary | None = None,
                 loop_closer: LoopCloser | None = None):
        self.tracker = tracker
        self.keyframe_policy = keyframe_policy
        self.mapper = mapper
        self.gaussian_map = gaussian_map
        self.growth = growth
        self.iterations_per_frame = iterations_per_frame
        self.boundary = boundary or PluginBoundary({})
        self.loop_closer = loop_closer or LoopCloser(boundary=self.boundary)
        self.num_keyframes = 0
        self.keyframes_in_target = 0  # keyframes (ids below this) whose Gaussians the tracker's target was built with
        self.last_pose: np.ndarray | None = None
        self.handover: KeyframeHandover | None = None  # the last keyframe going to the mapper beside tracking
        self.handover_time_s = 0.0
        self.handover_wait_s = 0.0

    def initialize(self, first_pose: np.ndarray) -> None:
        """Set the pose (camera-to-world) the trajectory starts from."""
        with self.boundary("tracker", "initialize"):
            self.tracker.initialize(first_pose)
        self.last_pose = first_pose

    def step(self, frame: Frame) -> StepResult:
        """Track one frame, have the loop closure decide on its keyframe at once and apply the
        decision, then run this frame's mapping iterations (sequential mode)."""
        step = self.track(frame)
        self.loop_closer.detect()
        step = self.close_loops(step)
        start = time.perf_counter()
        step.mapping_iterations = self.optimize(self.iterations_per_frame)
        step.mapping_time_s = time.perf_counter() - start
        return step

    def optimize(self, iterations: int) -> int:
        """Up to `iterations` mapping steps; the steps done."""
        with self.boundary("mapper", "optimize"):
            return self.mapper.optimize(iterations)

    def track(self, frame: Frame, defer_keyframe: bool = False) -> StepResult:
        """Track one frame and, if it is a keyframe, grow the map (real-time mode maps in
        another thread: see `MappingThread`); defer_keyframe: the mapper takes the keyframe in
        a thread of its own (`add_keyframe`)."""
        start = time.perf_counter()
        with self.boundary("tracker", "track"):
            result = self.tracker.track(frame)
        if not np.all(np.isfinite(result.pose)):  # a diverged tracker must not poison the map
            pose = self.last_pose if self.last_pose is not None else np.eye(4)
            result = TrackingResult(pose=pose.copy(), lost=True, stats={"lost_reason": "non-finite pose from tracker"})
        self.last_pose = result.pose
        if result.lost:
            decision = KeyframeDecision(KeyframeKind.NONE)
        else:
            with self.boundary("keyframe", "decide"):
                decision = self.keyframe_policy.decide(frame, result)
        if decision.kind:
            self.add_keyframe(frame, result, decision.kind, defer_keyframe)
        return self.close_loops(StepResult(result, decision, time.perf_counter() - start, 0.0, 0))

    def close_loops(self, step: StepResult) -> StepResult:
        """`step` after the loop closure's decisions made by now are applied (`correct`)."""
        correction = self.correct()
        return step if correction is None else step.corrected(correction)

    def correct(self) -> Correction | None:
        """Apply the loop closure's decisions made by now: each keyframe's Gaussians and training
        view move with its correction (`Mapper.move_keyframes`), the tracker follows the newest
        keyframe's and aligns to the moved map from now on. Returns the correction (the run's
        trajectory follows it), or None."""
        start = time.perf_counter()
        correction = self.loop_closer.take(self.num_keyframes)
        if correction is None:
            return None
        self.settle()  # the mapper has every keyframe the correction moves
        with self.boundary("mapper", "move_keyframes"):
            self.mapper.move_keyframes(correction.updates)
        with self.boundary("tracker", "move_world"):
            self.tracker.move_world(correction.current)
        with self.boundary("tracker", "update_target"):
            self.tracker.update_target(self.gaussian_map)
        self.keyframes_in_target = self.num_keyframes
        self.last_pose = correction.current @ self.last_pose
        self.loop_closer.cost.apply_s += time.perf_counter() - start
        return correction

    def add_keyframe(self, frame: Frame, result: TrackingResult, kind: KeyframeKind, defer: bool = False) -> None:
        """The keyframe's Gaussians enter the map (`grow_map`: the trackable ones, and those of
        the others that the mapper admits), a tracking keyframe rebuilds the tracker's target, the
        mapper and the loop closure take the keyframe. defer: what the next frames' tracking does
        not need runs in a `KeyframeHandover` thread beside it: the mapper taking the keyframe
        (`Mapper.add_keyframe`: a training view, the memory cap); for a tracking keyframe the
        admission of its Gaussians that are not trackable (its trackable ones, the tracker's next
        target, enter first on the tracking thread); for a mapping-only keyframe its whole growth
        (the tracker aligns to the map as of the last tracking keyframe). The next keyframe, a
        loop correction and a checkpoint wait for it (`settle`)."""
        self.settle()  # keyframes reach the map and the mapper in order, each before the next one's admission
        keyframe_id = self.num_keyframes
        if defer and kind is KeyframeKind.MAPPING_ONLY:  # Gaussians the tracker did not hand over: made there too
            self._start_handover(lambda: self._hand_over(frame, result.pose, kind, self.grow_map(
                frame, self.with_gaussians(frame, result), kind, keyframe_id)))
        elif defer and kind is KeyframeKind.TRACKING:
            new = self.candidate_rows(frame, self.with_gaussians(frame, result), kind, keyframe_id)
            trackable = None if new is None else new.trackable.cpu().numpy()
            tracked = self.gaussian_map.append(new.select(trackable).computed()) if new is not None else None
            self._update_target(keyframe_id)

            def hand_over() -> None:
                rows = self.grow_map(frame, result, kind, keyframe_id, None if new is None else new.select(~trackable))
                if tracked is not None and rows.start == tracked.stop > tracked.start:
                    rows = slice(tracked.start, rows.stop)  # nothing entered between: one keyframe's rows
                self._hand_over(frame, result.pose, kind, rows)
            self._start_handover(hand_over)
        else:
            rows = self.grow_map(frame, self.with_gaussians(frame, result), kind, keyframe_id)
            if kind is KeyframeKind.TRACKING:
                self._update_target(keyframe_id)
            if defer:
                self._start_handover(lambda: self._hand_over(frame, result.pose, kind, rows))
            else:
                self._hand_over(frame, result.pose, kind, rows)
        self.loop_closer.add_keyframe(keyframe_id, frame, result.pose, result.gaussians)  # what the tracker handed over
        self.num_keyframes += 1

    def _update_target(self, keyframe_id: int) -> None:
        """The tracker aligns to the map with keyframe `keyframe_id`'s trackable Gaussians in it."""
        with self.boundary("tracker", "update_target"):
            self.tracker.update_target(self.gaussian_map)
        self.keyframes_in_target = keyframe_id + 1

    def _start_handover(self, hand_over: Callable[[], None]) -> None:
        self.handover = KeyframeHandover(hand_over)
        self.handover.start()

    def _hand_over(self, frame: Frame, pose: np.ndarray, kind: KeyframeKind, rows: slice) -> None:
        """The mapper takes the keyframe; then the C heap's free pages go back to the OS."""
        with self.boundary("mapper", "add_keyframe"):
            self.mapper.add_keyframe(frame, pose, kind, rows)
        release_free_memory()

    def settle(self) -> None:
        """Wait for the keyframe going to the mapper beside tracking, if one is; raise its
        failure here (on the tracking thread)."""
        handover = self.handover
        if handover is None:
            return
        start = time.perf_counter()
        handover.join()  # an interrupt here leaves it to the next settle()
        self.handover = None
        self.handover_wait_s += time.perf_counter() - start
        self.handover_time_s += handover.seconds
        if handover.error is not None:
            raise handover.error

    def finish(self) -> None:
        """The mapper's wrap-up after the stream and the refinement."""
        with self.boundary("mapper", "finish"):
            self.mapper.finish()

    def save_map(self, out_dir) -> list:
        """The mapper's map files written into `out_dir` (none for a mapper that keeps none)."""
        with self.boundary("mapper", "save_map"):
            return list(self.mapper.save_map(out_dir) or [])

    def evaluate(self, frames, poses: list[np.ndarray], out_dir) -> dict:
        """The mapper's rendering metrics of the trajectory `poses` (camera-to-world)."""
        with self.boundary("mapper", "evaluate"):
            return self.mapper.evaluate(frames, poses, out_dir)

    def plugin_states(self) -> dict[str, dict]:
        """Each role's `state_dict()` by role key, for a checkpoint (call under the map's lock)."""
        states = {}
        for key, plugin in (("tracker", self.tracker), ("keyframe", self.keyframe_policy), ("mapper", self.mapper)):
            with self.boundary(key, "state_dict"):
                states[key] = plugin.state_dict()
        states["loop_closure"] = self.loop_closer.state_dict()
        return states

    def load_plugin_states(self, states: dict[str, dict]) -> None:
        """Take back `plugin_states()` (after the map's rows and the last pose are restored)."""
        if self.last_pose is not None:
            self.initialize(self.last_pose)  # a tracker that saves nothing goes on from the last pose
        for key, plugin in (("tracker", self.tracker), ("keyframe", self.keyframe_policy), ("mapper", self.mapper)):
            with self.boundary(key, "load_state_dict"):
                plugin.load_state_dict(states.get(key, {}))
        self.loop_closer.load_state_dict(states.get("loop_closure", {}))

    def with_gaussians(self, frame: Frame, result: TrackingResult) -> TrackingResult:
        """`result` with the keyframe's Gaussians: the tracker's when it handed them over, else
        made by the map's growth from the frame at the tracked pose (`frame_gaussians`) when the
        mapper grows the map from frames (`Mapper.grows_from_frames`); their world covariances
        and colours are computed when first read."""
        if result.gaussians is not None or not self.mapper.grows_from_frames:
            return result
        gm = self.gaussian_map
        return replace(result, gaussians=frame_gaussians(frame, result.pose, self.growth,
                                                         gm.trackable_entry_means(0) if len(gm) else np.empty((0, 3))))

    def candidate_rows(self, frame: Frame, result: TrackingResult, kind: KeyframeKind,
                       keyframe_id: int) -> GaussianRows | None:
        """Keyframe `keyframe_id`'s Gaussians as map rows (scale-aligned, paper Sec. 3.1), not yet
        in the map (a mapping-only keyframe's trackable or not: `growth.mapping_only_trackable`);
        None when it has none."""
        if result.gaussians is None:
            return None
        gm = self.gaussian_map
        return new_gaussians(result.gaussians, keyframe_id, self.growth, gm.device,
                             gm.trackable_entry_means(self.keyframes_in_target),
                             mapping_only=kind is KeyframeKind.MAPPING_ONLY)

    def grow_map(self, frame: Frame, result: TrackingResult, kind: KeyframeKind, keyframe_id: int | None = None,
                 candidates: GaussianRows | None = None) -> slice:
        """Keyframe `keyframe_id`'s Gaussians (None: the next, `num_keyframes`; `candidates`:
        those of its `candidate_rows` still to enter) enter the map: the trackable ones, and those
        of the others that the mapper admits (`Mapper.admit`); returns the rows they occupy."""
        gm = self.gaussian_map
        keyframe_id = self.num_keyframes if keyframe_id is None else keyframe_id
        new = candidates if candidates is not None else self.candidate_rows(frame, result, kind, keyframe_id)
        if new is None:
            return slice(len(gm), len(gm))
        with gm.lock, self.boundary("mapper", "admit"):
            admitted = self.mapper.admit(frame, result.pose, new)
        if admitted is not None:  # the trackable rows enter whatever the mapper says (the tracker's target)
            admitted = np.asarray(torch.as_tensor(admitted).cpu(), dtype=bool) | new.trackable.cpu().numpy()
        entering = (new if admitted is None else new.select(admitted)).computed()  # outside the lock
        return gm.append(entering)


class KeyframeHandover(threading.Thread):
    """A keyframe's work that tracking does not wait for (`SLAM.add_keyframe(..., defer=True)`):
    `hand_over()` in a thread of its own, at the tracking thread's priority (the mapping
    thread's lower one would let training hold up the next keyframe). `error`: what it raised,
    for `SLAM.settle` to raise on the tracking thread; `seconds`: how long it took."""

    def __init__(self, hand_over: Callable[[], None]):
        super().__init__(name="slamkit-keyframe", daemon=True)
        self.hand_over = hand_over
        self.error: BaseException | None = None
        self.seconds = 0.0

    def run(self) -> None:
        start = time.perf_counter()
        try:
            self.hand_over()
        except BaseException as exc:  # raised again by SLAM.settle on the tracking thread
            self.error = exc
        finally:
            self.seconds = time.perf_counter() - start


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


class MappingThread(threading.Thread):
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
        super().__init__(name="slamkit-mapping", daemon=True)
        self.slam = slam
        self.switch_interval_s = switch_interval_s
        self.priority = ThreadPriority(priority)
        self._saved_switch_interval: float | None = None
        self.iterations = 0
        self.busy_time_s = 0.0
        self.cpu_time_s = 0.0  # the thread's CPU seconds (steps, waits' overhead), when it ends
        self.throttle = MappingThrottle(self.priority.value)  # complete when it ends
        self.error: BaseException | None = None
        self._stop_event = threading.Event()
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

    def check(self) -> None:
        """Re-raise a mapper failure in the calling (tracking) thread."""
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        self._stop_event.set()
        self._tracking_done.set()
        if self.is_alive():
            self.join()
        if self._saved_switch_interval is not None:
            sys.setswitchinterval(self._saved_switch_interval)
            self._saved_switch_interval = None
        self.check()
