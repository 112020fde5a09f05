"""Loop closure inside the running system: `LoopCloser` hands each keyframe to the run's
`slamkit.roles.loop_closure.LoopClosure`, has it decide (`detect_and_optimise`) in the tracking
thread after the keyframe (sequential mode: deterministic) or, in real time, in a process of its
own at the mapping thread's priority (`slamkit.run.loop_process`) that a thread of this one waits
on (`slamkit.run.workers.LoopThread`), and hands the decisions to the
tracking thread as one `Correction` between two frames (`SLAM.correct` applies it: the map's
Gaussians and the mapper's keyframes move, the tracker follows; the run's trajectory follows
through `Correction.follow`).

Tracking never waits on detection: the tracking thread only queues a keyframe (its points in
the camera frame, a small image) and, between frames, takes the decisions made by then. A
keyframe tracked while a decision was being made carries the world it was tracked in
(`LoopKeyframe.world`), and the loop closure places it in the newer one itself. Checkpoints hold
the loop closure's state with the keyframes it has not taken yet and the decisions not applied
yet (`state_dict`), so a resumed run goes on with the same graph.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from slamkit.geometry.pose_graph import PoseGraph, follow_keyframes, owning_keyframes, pose_difference
from slamkit.geometry.transforms import invert_pose, transform_points
from slamkit.roles.loop_closure import LoopCheck, LoopClosure, LoopDecision, LoopKeyframe
from slamkit.run.boundary import PluginBoundary
from slamkit.run.loop_process import LoopClosureProcess
from slamkit.types import Frame, FrameGaussians

log = logging.getLogger(__name__)

#: The keyframe image given for appearance is the frame's colour image averaged over blocks of
#: this many pixels a side (80x60 from 640x480): the appearance descriptor is 32x24.
IMAGE_BLOCK = 8
#: loops.csv's columns: LoopCheck.COLUMNS, then whether the loop is in the final pose graph and why not.
LOOPS_COLUMNS = (*LoopCheck.COLUMNS, "accepted", "reason")


def block_average(image: np.ndarray, block: int) -> np.ndarray:
    """(H,W,C) image averaged over block x block pixels (the edge rows and columns that do not
    fill a block dropped), same dtype."""
    h, w = image.shape[0] // block * block, image.shape[1] // block * block
    blocks = image[:h, :w].reshape(h // block, block, w // block, block, -1).astype(np.float32)
    return blocks.mean(axis=(1, 3)).round().astype(image.dtype)


def loop_keyframe(keyframe_id: int, frame: Frame, pose: np.ndarray, gaussians: FrameGaussians | None,
                  world: int) -> LoopKeyframe:
    """A keyframe as the loop closure takes it: its trackable Gaussian centres, their
    covariances (as the tracker aligned them) in its camera frame (float32, metres and m^2) and
    colours (float32 RGB in [0, 1]), its colour image block-averaged (`IMAGE_BLOCK`), its pose as
    tracked (camera-to-world)."""
    world_to_camera = invert_pose(np.asarray(pose, dtype=np.float64))
    if gaussians is None:
        points, covariances, colours = np.zeros((0, 3), np.float32), None, None
    else:
        keep = np.asarray(gaussians.trackable, dtype=bool)
        R = world_to_camera[:3, :3]
        points = transform_points(world_to_camera, np.asarray(gaussians.means, dtype=np.float64)[keep])
        covariances = (R @ np.asarray(gaussians.covariances, dtype=np.float64)[keep] @ R.T).astype(np.float32)
        colours = np.asarray(gaussians.colors, dtype=np.float32)[keep]
        points = points.astype(np.float32)
    image = block_average(np.asarray(frame.rgb), IMAGE_BLOCK) if frame.rgb is not None else None
    return LoopKeyframe(keyframe_id, frame.index, pose, points, covariances, image, world=world, colours=colours)


@dataclass(frozen=True)
class Correction:
    """Loop-closure decisions as the run applies them between two frames. updates: (K,4,4)
    float64, the world-frame rigid motion of each keyframe 0..K-1 of the run (corrected pose =
    updates[k] @ pose): keyframes of the pose graph by its optimisation, later ones (tracked
    while it was made) by the last graph keyframe's. What a keyframe placed in the world, its
    Gaussians and the frames tracked from it, moves with it."""

    updates: np.ndarray

    @property
    def current(self) -> np.ndarray:
        """The newest keyframe's motion: the tracker's and every later frame's."""
        return self.updates[-1]

    @classmethod
    def of(cls, decision: LoopDecision, num_keyframes: int) -> Correction:
        """`decision`'s updates spread over the run's `num_keyframes` keyframes (a keyframe the
        graph does not hold follows the last graph keyframe before it)."""
        ids = np.array(sorted(decision.updates), dtype=np.int64)
        motions = np.array([decision.updates[int(k)] for k in ids], dtype=np.float64)
        return cls(motions[owning_keyframes(np.arange(num_keyframes), ids)])

    def covering(self, num_keyframes: int) -> Correction:
        """This correction of at least keyframes 0..num_keyframes-1 (those it does not cover move
        with its newest keyframe)."""
        missing = max(num_keyframes - len(self.updates), 0)
        return Correction(np.concatenate([self.updates, np.repeat(self.current[None], missing, axis=0)]))

    def then(self, later: Correction) -> Correction:
        """This correction followed by `later` (a keyframe one of them does not cover moved with
        its newest keyframe)."""
        n = max(len(self.updates), len(later.updates))
        return Correction(later.covering(n).updates @ self.covering(n).updates)

    def follow(self, poses: np.ndarray, keyframe_positions) -> np.ndarray:
        """(F,4,4) camera-to-world `poses` of a trajectory moved with their keyframes:
        keyframe_positions (K',) the positions in `poses` of keyframes 0..K'-1 (K' <= K, the ones
        recorded so far): each frame follows the last keyframe at or before it (the ones before
        the first, the first)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        positions = np.asarray(keyframe_positions, dtype=np.int64)
        if len(positions) == 0:
            return self.updates[0] @ poses
        return follow_keyframes(poses, np.arange(len(poses)), positions, self.updates[:len(positions)])

    def largest(self) -> tuple[float, float]:
        """(metres, degrees): the largest keyframe motion of this correction."""
        moves = [pose_difference(np.eye(4), u) for u in self.updates]
        return max(m for m, _ in moves), max(d for _, d in moves)


@dataclass
class LoopClosureCost:
    """What the loop closure cost, over the whole run: keyframes it took, its calls, CPU and
    wall seconds in its calls (CPU: its process's in real time, threads included; in sequential
    mode the tracking thread's, where open3d's OpenMP workers are not counted unless
    OMP_NUM_THREADS=1), and the tracking thread's seconds applying
    corrections (moving the map, rebuilding the tracker's target); the corrections applied and
    the largest keyframe motion of one."""

    keyframes: int = 0
    calls: int = 0
    cpu_s: float = 0.0
    wall_s: float = 0.0
    apply_s: float = 0.0
    corrections: int = 0
    largest_correction_m: float = 0.0
    largest_correction_deg: float = 0.0
    after_stream: int = 0  # keyframes not taken yet when the stream ended (real time: the loop thread's backlog)
    graph_cpu_s: float = 0.0  # CPU seconds reading the graph for pose_graph.g2o (work a plugin left until then)


def _keyframe_state(k: LoopKeyframe) -> dict[str, Any]:
    return {"keyframe_id": k.keyframe_id, "frame_index": k.frame_index, "pose": k.pose, "points": k.points,
            "covariances": k.covariances, "image": k.image, "odometry_information": k.odometry_information,
            "world": k.world, "colours": k.colours}


def _keyframe_from_state(s: dict[str, Any]) -> LoopKeyframe:
    def array(v):
        return None if v is None else np.asarray(v)

    return LoopKeyframe(int(s["keyframe_id"]), int(s["frame_index"]), np.asarray(s["pose"], dtype=np.float64),
                        np.asarray(s["points"]), array(s["covariances"]), array(s["image"]),
                        array(s["odometry_information"]), int(s["world"]),
                        array(s.get("colours")))  # older checkpoints: none


def _row(check: LoopCheck) -> dict[str, Any]:
    return {**check.row(), "accepted": check.accepted, "reason": check.reason}


class LoopCloser:
    """The run's loop closure (`closure`, None or one whose `closes_loops` is False: inactive,
    it takes nothing and decides nothing): keyframes in, corrections out (module docstring).

    The plugin is called by one thread at a time (`_plugin_lock`): the loop thread in real time,
    else the tracking thread. Every candidate it verified is kept as a loops.csv row (`rows`; a
    loop a later optimisation dropped is marked rejected with the reason).

    `at_end` (`loop_corrections=at_end`): the decisions wait until the stream has ended, so that
    the tracker and its map stay in odometry's frame and every keyframe reaches the loop closure
    as tracked; one correction then moves everything (docs/loop_closure.md)."""

    def __init__(self, closure: LoopClosure | None = None, boundary: PluginBoundary | None = None,
                 at_end: bool = False):
        self.closure = closure
        self.active = closure is not None and closure.closes_loops
        self.at_end = at_end
        self.boundary = boundary or PluginBoundary({})
        self.applied_world = 0  # the world of the last decision applied (LoopKeyframe.world)
        # at_end: the decisions taken so far, folded into one correction, and the newest one's world
        self._held: Correction | None = None
        self._held_world = 0
        self.cost = LoopClosureCost()
        self.loop_segments = np.zeros((0, 2, 3))  # accepted loops' camera-centre pairs (viewers)
        self._rows: dict[tuple[int, int], dict[str, Any]] = {}
        self._queued: list[LoopKeyframe] = []
        self._decisions: list[LoopDecision] = []
        self._centres: dict[int, np.ndarray] = {}
        self._wake = threading.Condition()  # guards _queued, _decisions, _rows; wakes the loop thread
        self._plugin_lock = threading.Lock()

    # -- the tracking thread -------------------------------------------------------------------
    def add_keyframe(self, keyframe_id: int, frame: Frame, pose: np.ndarray, gaussians: FrameGaussians | None) -> None:
        """Queue keyframe `keyframe_id` (its points, image and pose as tracked) for the loop
        closure. Cheap: the work is `detect`'s or the loop thread's."""
        if not self.active:
            return
        keyframe = loop_keyframe(keyframe_id, frame, pose, gaussians, self.applied_world)
        with self._wake:
            self._queued.append(keyframe)
            self._centres[keyframe_id] = np.asarray(pose, dtype=np.float64)[:3, 3].copy()
            self._wake.notify_all()

    def take(self, num_keyframes: int, stream_ended: bool = False) -> Correction | None:
        """The decisions made since the last call, as one correction of the run's
        `num_keyframes` keyframes (None when none moved a keyframe, or while `at_end` holds them
        and the stream goes on). The caller applies it (`SLAM.correct`) before the next keyframe
        is queued."""
        if not self.active:
            return None
        with self._wake:
            decisions, self._decisions = self._decisions, []
        held = self._held  # folded as they come, so that holding them costs one correction's memory
        for decision in decisions:
            self._held_world = max(self._held_world, decision.world)
            if decision:
                step = Correction.of(decision, num_keyframes)
                held = step if held is None else held.then(step)
        self._held = held
        if self.at_end and not stream_ended:
            if any(decisions):
                self._update_segments()  # the loops, between the keyframes' centres as tracked
            return None
        correction, self._held = self._held, None
        self.applied_world = max(self.applied_world, self._held_world)
        if correction is not None:
            correction = correction.covering(num_keyframes)  # keyframes since the last decision too
            for k, centre in self._centres.items():  # each keyframe's centre moves with it
                motion = correction.updates[k]
                self._centres[k] = motion[:3, :3] @ centre + motion[:3, 3]
            self.cost.corrections += 1
            largest_m, largest_deg = correction.largest()
            self.cost.largest_correction_m = max(self.cost.largest_correction_m, largest_m)
            self.cost.largest_correction_deg = max(self.cost.largest_correction_deg, largest_deg)
        if decisions or correction is not None:
            self._update_segments()
        return correction

    # -- deciding (the loop thread, or the tracking thread in sequential mode) ------------------
    def detect(self, limit: int | None = None) -> bool:
        """Give the queued keyframes (the first `limit` of them; None: all) to the loop closure
        and have it decide now; the decision waits for `take`. False when nothing was queued."""
        if not self.active:
            return False
        with self._plugin_lock:
            with self._wake:
                batch, self._queued = self._queued[:limit], self._queued[len(self._queued[:limit]):]
            if not batch:
                return False
            wall, cpu = time.perf_counter(), self._cpu_clock()
            for keyframe in batch:
                with self.boundary("loop_closure", "add_keyframe"):
                    self.closure.add_keyframe(keyframe)
            with self.boundary("loop_closure", "detect_and_optimise"):
                decision = self.closure.detect_and_optimise()
            self.cost.keyframes += len(batch)
            self.cost.calls += 1
            self.cost.cpu_s += self._cpu_clock() - cpu
            self.cost.wall_s += time.perf_counter() - wall
            with self._wake:
                self._decisions.append(decision)
                for check in decision.checks:
                    self._rows[(check.keyframe_id, check.match_id)] = _row(check)
        for check in decision.accepted:
            log.info("loop closed: frame %d -> %d (fitness %.3f, %d inliers; %.1f cm, %.2f deg from odometry)",
                     check.frame_index, check.match_frame_index, check.fitness, check.inliers,
                     100 * check.correction_m, check.correction_deg)
        return True

    def _cpu_clock(self) -> float:
        """CPU seconds so far of whoever runs the loop closure: its process (real time, its
        threads included) or this thread (sequential)."""
        return self.closure.cpu_s if isinstance(self.closure, LoopClosureProcess) else time.thread_time()

    def close(self) -> None:
        """End the loop closure's process, if it has one (after the run's last call)."""
        if isinstance(self.closure, LoopClosureProcess):
            self.closure.close()

    def finish_stream(self, check_stop: Callable[[], None] = lambda: None) -> None:
        """After the stream (the loop thread stopped): decide on the keyframes not taken yet,
        one call per keyframe as in sequential mode, `check_stop()` before each (a stop signal:
        it raises, and the keyframes not taken stay queued, kept by the checkpoint)."""
        self.cost.after_stream = self.waiting()
        while self.waiting():
            check_stop()
            self.detect(limit=1)

    def waiting(self) -> int:
        """Keyframes waiting for `detect`."""
        with self._wake:
            return len(self._queued)

    def wait_for_keyframes(self, timeout_s: float) -> None:
        """Block until a keyframe is queued or `timeout_s` passed (the loop thread's idle wait)."""
        with self._wake:
            if not self._queued:
                self._wake.wait(timeout_s)

    def wake(self) -> None:
        with self._wake:
            self._wake.notify_all()

    # -- what the run writes -------------------------------------------------------------------
    def rows(self) -> list[dict[str, Any]]:
        """loops.csv's rows (`LOOPS_COLUMNS`), in the order the candidates were verified."""
        with self._wake:
            return list(self._rows.values())

    def pose_graph(self) -> PoseGraph:
        """The loop closure's pose graph as it stands (for pose_graph.g2o)."""
        with self._plugin_lock, self.boundary("loop_closure", "pose_graph"):
            cpu = self._cpu_clock()
            graph = self.closure.pose_graph()
            self.cost.graph_cpu_s += self._cpu_clock() - cpu
            return graph

    def metrics(self) -> dict[str, Any]:
        """metrics.json's loop-closure figures ({} when inactive)."""
        if not self.active:
            return {}
        rows = self.rows()
        c = self.cost
        return {"loops_accepted": sum(bool(r["accepted"]) for r in rows),
                "loops_rejected": sum(not r["accepted"] for r in rows),
                "loop_corrections": c.corrections, "loop_correction_max_m": c.largest_correction_m,
                "loop_correction_max_deg": c.largest_correction_deg, "loop_closure_keyframes": c.keyframes,
                "loop_closure_calls": c.calls, "loop_closure_cpu_s": c.cpu_s, "loop_closure_wall_s": c.wall_s,
                "loop_closure_cpu_s_per_keyframe": c.cpu_s / c.keyframes if c.keyframes else None,
                "loop_closure_apply_s": c.apply_s, "loop_keyframes_after_stream": c.after_stream,
                "loop_closure_graph_cpu_s": c.graph_cpu_s}

    # -- checkpoints ---------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The loop closure's state (its plugin's `state_dict`), the keyframes it has not taken
        yet, the decisions not applied yet, the rows and the costs. In real time this waits for
        the loop thread's current call to end."""
        if not self.active:
            return {}
        with self._plugin_lock:
            with self.boundary("loop_closure", "state_dict"):
                plugin = self.closure.state_dict()
            with self._wake:
                queued, decisions, rows = list(self._queued), list(self._decisions), list(self._rows.values())
        pending = [{"world": d.world, "ids": np.array(sorted(d.updates), dtype=np.int64),
                    "updates": np.array([d.updates[k] for k in sorted(d.updates)]).reshape(-1, 4, 4)}
                   for d in decisions]
        held = None if self._held is None else {"world": self._held_world, "updates": self._held.updates}
        return {"plugin": plugin, "queued": [_keyframe_state(k) for k in queued], "decisions": pending,
                "held": held, "applied_world": self.applied_world, "rows": rows,
                "centres": {"ids": np.array(sorted(self._centres), dtype=np.int64),
                            "centres": np.array([self._centres[k] for k in sorted(self._centres)]).reshape(-1, 3)},
                "cost": dict(vars(self.cost))}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()` (before the next frame)."""
        if not self.active or not state:
            return
        with self._plugin_lock:
            with self.boundary("loop_closure", "load_state_dict"):
                self.closure.load_state_dict(state["plugin"])
            with self._wake:
                self._queued = [_keyframe_from_state(k) for k in state["queued"]]
                self._decisions = [LoopDecision(updates={int(k): np.asarray(u, dtype=np.float64)
                                                         for k, u in zip(d["ids"], d["updates"])},
                                                world=int(d["world"])) for d in state["decisions"]]
                self._rows = {(int(r["keyframe"]), int(r["match_keyframe"])): dict(r) for r in state["rows"]}
        self.applied_world = int(state["applied_world"])
        held = state.get("held")  # checkpoints before loop_corrections have none
        self._held = None if held is None else Correction(np.asarray(held["updates"], dtype=np.float64))
        self._held_world = self.applied_world if held is None else int(held["world"])
        centres = state["centres"]
        self._centres = {int(k): np.asarray(c, dtype=np.float64) for k, c in zip(centres["ids"], centres["centres"])}
        self.cost = LoopClosureCost(**{k: type(getattr(LoopClosureCost(), k))(v) for k, v in state["cost"].items()})
        self._update_segments()

    def _update_segments(self) -> None:
        pairs = [(r["match_keyframe"], r["keyframe"]) for r in self.rows() if r["accepted"]]
        pairs = [(m, k) for m, k in pairs if m in self._centres and k in self._centres]
        self.loop_segments = np.array([[self._centres[m], self._centres[k]] for m, k in pairs]).reshape(-1, 2, 3)
