"""The SLAM loop over one shared Gaussian map, free of I/O (see `slamkit.run.pipeline` for that)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.map.growth import MapGrowthConfig, frame_gaussians, new_gaussians
from slamkit.roles import KeyframeDecision, KeyframePolicy, Mapper, Tracker
from slamkit.run.boundary import PluginBoundary
from slamkit.run.handover import KeyframeHandovers
from slamkit.run.heap import release_free_memory
from slamkit.run.loop_closing import Correction, LoopCloser
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
    """GS-ICP SLAM: a tracker and a mapper sharing one GaussianMap. `process(frame)` is its one
    per-frame method, in every mode.

    Each frame is tracked against the map; a keyframe's Gaussians that the mapper admits enter
    the map (a tracking keyframe also rebuilds the tracker's target from the map, which by then
    holds the mapper's optimised values); every keyframe goes to the loop closure
    (`loop_closer`), and when it corrects the keyframes, the map's Gaussians and the mapper's
    keyframes move with them and the tracker follows (`correct`). After each keyframe the C
    heap's free pages go back to the OS (`slamkit.run.heap`), so that a long run's resident
    memory follows what it holds. Every call into a plugin passes `boundary`, which names the
    plugin a failure came from.

    What else a frame's call does is fixed by the constructor. Sequential mode
    (`beside=False`): the loop closure decides on the frame's keyframe at once and the mapper
    then runs `iterations_per_frame` steps, so the run is deterministic. Real time
    (`beside=True`): the map is trained and loops decided by the workers of
    `slamkit.run.runner.RealtimeRunner` beside tracking, and with `handovers` the mapper takes a
    keyframe in a thread of its own (`KeyframeHandovers`) while the next frames are tracked; a
    tracking keyframe's trackable Gaussians enter the map on the tracking thread, the tracker's
    new target is built first in the keyframe's thread, and the next frame waits for it, so it
    aligns to the map with the keyframe in it.
    """

    def __init__(self, tracker: Tracker, keyframe_policy: KeyframePolicy, mapper: Mapper, gaussian_map: GaussianMap,
                 growth: MapGrowthConfig, iterations_per_frame: int = 0, boundary: PluginBoundary | None = None,
                 loop_closer: LoopCloser | None = None, beside: bool = False,
                 handovers: KeyframeHandovers | None = None):
        self.tracker = tracker
        self.keyframe_policy = keyframe_policy
        self.mapper = mapper
        self.gaussian_map = gaussian_map
        self.growth = growth
        self.iterations_per_frame = iterations_per_frame
        self.beside = beside  # real time: mapping and loop detection run beside `process`, not in it
        self.handovers = handovers  # None: the mapper takes each keyframe on the calling thread
        self.boundary = boundary or PluginBoundary({})
        self.loop_closer = loop_closer or LoopCloser(boundary=self.boundary)
        self.num_keyframes = 0
        self.keyframes_in_target = 0  # keyframes (ids below this) whose Gaussians the tracker's target was built with
        self.last_pose: np.ndarray | None = None

    def initialize(self, first_pose: np.ndarray) -> None:
        """Set the pose (camera-to-world) the trajectory starts from."""
        with self.boundary("tracker", "initialize"):
            self.tracker.initialize(first_pose)
        self.last_pose = first_pose

    def process(self, frame: Frame) -> StepResult:
        """One frame: tracked (the first one placed at its ground-truth pose, else the origin),
        its keyframe, if it is one, into the map, the mapper and the loop closure, the loop
        closure's decisions made by now applied; in sequential mode the loop closure then
        decides on the keyframe and the mapper trains `iterations_per_frame` steps."""
        if self.last_pose is None:  # the run's first frame (a resumed run has its last pose)
            self.initialize(frame.gt_pose if frame.gt_pose is not None else np.eye(4))
        start = time.perf_counter()
        if self.handovers is not None:
            self.handovers.ready()  # the tracker's target with the last tracking keyframe in it
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
            self.add_keyframe(frame, result, decision.kind)
        step = self.close_loops(StepResult(result, decision, time.perf_counter() - start, 0.0, 0))
        if self.beside:
            return step
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

    def close_loops(self, step: StepResult) -> StepResult:
        """`step` after the loop closure's decisions made by now are applied (`correct`)."""
        correction = self.correct()
        return step if correction is None else step.corrected(correction)

    def correct(self, stream_ended: bool = False) -> Correction | None:
        """Apply the loop closure's decisions made by now (with `loop_corrections=at_end`, only
        once `stream_ended`): each keyframe's Gaussians and training view move with its
        correction (`Mapper.move_keyframes`), the tracker follows the newest keyframe's and
        aligns to the moved map from now on. Returns the correction (the run's trajectory
        follows it), or None."""
        start = time.perf_counter()
        correction = self.loop_closer.take(self.num_keyframes, stream_ended)
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

    def add_keyframe(self, frame: Frame, result: TrackingResult, kind: KeyframeKind) -> None:
        """The keyframe's Gaussians enter the map (`grow_map`: the trackable ones, and those of
        the others that the mapper admits), a tracking keyframe rebuilds the tracker's target, the
        mapper and the loop closure take the keyframe. With `handovers`, what the next frames'
        tracking does not need runs in a thread beside it: the mapper taking the keyframe
        (`Mapper.add_keyframe`: a training view, the memory cap); for a tracking keyframe the
        admission of its Gaussians that are not trackable (its trackable ones enter first on the
        tracking thread; the tracker's new target is built from them first in the thread, and the
        next frame waits for that part: `KeyframeHandovers.ready`); for a mapping-only keyframe
        its whole growth (the tracker aligns to the map as of the last tracking keyframe). The
        next keyframe, a loop correction and a checkpoint wait for it (`settle`)."""
        self.settle()  # keyframes reach the map and the mapper in order, each before the next one's admission
        keyframe_id = self.num_keyframes
        defer = self.handovers is not None
        if defer and kind is KeyframeKind.MAPPING_ONLY:  # Gaussians the tracker did not hand over: made there too
            self.handovers.start(lambda: self._hand_over(frame, result.pose, kind, self.grow_map(
                frame, self.with_gaussians(frame, result), kind, keyframe_id)))
        elif defer and kind is KeyframeKind.TRACKING:
            new = self.candidate_rows(frame, self.with_gaussians(frame, result), kind, keyframe_id)
            trackable = None if new is None else new.trackable.cpu().numpy()
            tracked = self.gaussian_map.append(new.select(trackable).computed()) if new is not None else None

            def hand_over() -> None:
                rows = self.grow_map(frame, result, kind, keyframe_id, None if new is None else new.select(~trackable))
                if tracked is not None and rows.start == tracked.stop > tracked.start:
                    rows = slice(tracked.start, rows.stop)  # nothing entered between: one keyframe's rows
                self._hand_over(frame, result.pose, kind, rows)
            # the new target first, before the rest changes the map: the next frame waits for it alone
            self.handovers.start(hand_over, first=lambda: self._update_target(keyframe_id))
        else:
            rows = self.grow_map(frame, self.with_gaussians(frame, result), kind, keyframe_id)
            if kind is KeyframeKind.TRACKING:
                self._update_target(keyframe_id)
            if defer:
                self.handovers.start(lambda: self._hand_over(frame, result.pose, kind, rows))
            else:
                self._hand_over(frame, result.pose, kind, rows)
        self.loop_closer.add_keyframe(keyframe_id, frame, result.pose, result.gaussians)  # what the tracker handed over
        self.num_keyframes += 1

    def _update_target(self, keyframe_id: int) -> None:
        """The tracker aligns to the map with keyframe `keyframe_id`'s trackable Gaussians in it."""
        with self.boundary("tracker", "update_target"):
            self.tracker.update_target(self.gaussian_map)
        self.keyframes_in_target = keyframe_id + 1

    def _hand_over(self, frame: Frame, pose: np.ndarray, kind: KeyframeKind, rows: slice) -> None:
        """The mapper takes the keyframe; then the C heap's free pages go back to the OS."""
        with self.boundary("mapper", "add_keyframe"):
            self.mapper.add_keyframe(frame, pose, kind, rows)
        release_free_memory()

    def settle(self) -> None:
        """Wait for the keyframe going to the mapper beside tracking, if one is; raise its
        failure here (on the tracking thread)."""
        if self.handovers is not None:
            self.handovers.settle()

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
