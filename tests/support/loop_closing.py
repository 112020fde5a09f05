"""A loop closure and a viewer for tests of loop closure inside the run: `shifting` moves every
keyframe by SHIFT once it has `after` keyframes (sleeping `sleep_s` a call, logging its process id),
`recording` keeps the last ViewerFrame; `loop_registry()` holds them, `run_shifted` runs the
synthetic sequence through it, `offsets` reads a run's position errors, and
`check_run_follows_shift` asserts that a run follows the shift, in either mode."""

from __future__ import annotations

import csv
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.formats.g2o import read_g2o
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry import make_pose
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import discover
from slamkit.roles import PluginConfig, Viewer, ViewerConfig, ViewerFrame
from slamkit.roles.loop_closure import LoopCheck, LoopClosure, LoopDecision, LoopKeyframe, PoseGraph, PoseGraphEdge
from slamkit.run import checkpoint, pipeline

#: The correction the shifting loop closure below makes: every keyframe 10 cm along x.
SHIFT = make_pose(np.eye(3), [0.10, 0.0, 0.0])


@dataclass
class ShiftingConfig(PluginConfig):
    """Test plugin: the decision after this many keyframes moves them all by SHIFT."""

    #: keyframes before the one decision that moves them
    after: int = 3
    #: keyframes before a second decision that moves them all by SHIFT again (0: none)
    again: int = 0
    #: seconds each detect_and_optimise sleeps (a slow loop closure)
    sleep_s: float = 0.0
    #: a file each detect_and_optimise appends its process id to (null: none)
    log: str | None = None


class ShiftingLoopClosure(LoopClosure):
    """Keeps its keyframes' poses (placed in the newest world); once it has `after` keyframes it
    reports one accepted loop (the last to the first) and moves every keyframe by SHIFT (and,
    with `again`, once more at that many keyframes)."""

    def __init__(self, cfg: ShiftingConfig, context=None):
        self.cfg = cfg
        self.poses: dict[int, np.ndarray] = {}
        self.frames: dict[int, int] = {}
        self.world_updates: list[np.ndarray] = []
        self.pending: list[LoopKeyframe] = []

    def add_keyframe(self, keyframe: LoopKeyframe) -> None:
        self.pending.append(keyframe)

    def detect_and_optimise(self) -> LoopDecision:
        if self.cfg.log:
            with open(self.cfg.log, "a") as f:
                f.write(f"{os.getpid()}\n")
        time.sleep(self.cfg.sleep_s)
        for k in self.pending:
            pose = k.pose
            for update in self.world_updates[k.world:]:
                pose = update @ pose
            self.poses[k.keyframe_id], self.frames[k.keyframe_id] = pose, k.frame_index
        self.pending = []
        due = self.cfg.after if not self.world_updates else self.cfg.again if len(self.world_updates) == 1 else 0
        if not due or len(self.poses) < due:
            return LoopDecision(world=len(self.world_updates))
        before = dict(self.poses)
        self.poses = {k: SHIFT @ p for k, p in self.poses.items()}
        self.world_updates.append(SHIFT)
        first, last = min(self.poses), max(self.poses)
        check = LoopCheck(last, first, self.frames[last], self.frames[first], np.eye(4), 0.9, 100, 0.005, 0.1, 0.0,
                          True)
        return LoopDecision((check,), dict(self.poses), {k: self.poses[k] @ np.linalg.inv(before[k]) for k in before},
                            world=len(self.world_updates))

    def pose_graph(self) -> PoseGraph:
        ids = sorted(self.poses)
        edges = tuple(PoseGraphEdge("odometry", a, b, np.linalg.inv(self.poses[a]) @ self.poses[b], np.eye(6))
                      for a, b in zip(ids, ids[1:]))
        return PoseGraph(np.array(ids), np.array([self.poses[k] for k in ids]).reshape(-1, 4, 4), edges)

    def state_dict(self) -> dict:
        return {"ids": np.array(sorted(self.poses), dtype=np.int64),
                "poses": np.array([self.poses[k] for k in sorted(self.poses)]).reshape(-1, 4, 4),
                "frames": [self.frames[k] for k in sorted(self.poses)], "world_updates": list(self.world_updates)}

    def load_state_dict(self, state: dict) -> None:
        self.poses = {int(k): np.asarray(p) for k, p in zip(state["ids"], state["poses"])}
        self.frames = {int(k): int(f) for k, f in zip(state["ids"], state["frames"])}
        self.world_updates = [np.asarray(u) for u in state["world_updates"]]


class RecordingViewer(Viewer):
    """Test viewer: keeps the last ViewerFrame it was shown, and the pose of each frame as it
    was shown (`poses`) and the loops shown with it (`loops`), since the last run built one."""

    last: ViewerFrame | None = None
    poses: list[np.ndarray] = []
    loops: list[int] = []

    def __init__(self, cfg: ViewerConfig, context=None):
        self.cfg = cfg
        RecordingViewer.poses, RecordingViewer.loops = [], []

    def show(self, view: ViewerFrame) -> None:
        RecordingViewer.last = view
        RecordingViewer.poses.append(np.array(view.pose))
        RecordingViewer.loops.append(len(view.loops))


@hookimpl
def slamkit_plugins():
    return [PluginSpec("shifting", ShiftingLoopClosure, ShiftingConfig),
            PluginSpec("recording", RecordingViewer, ViewerConfig)]


_registry = None


def loop_registry():
    """The installed plugins and this module's, in a registry of their own (the process's
    default registry stays what is installed: the composition matrix lists it)."""
    global _registry
    if _registry is None:
        _registry = discover()
        _registry.add_module(sys.modules[__name__], "tests/support/loop_closing.py")
    return _registry


def run_shifted(registry, out: Path, *overrides: str) -> dict:
    """The synthetic sequence's first 30 frames with `shifting`, corrections applied when made
    (`loop_corrections=during`) unless `overrides` say otherwise."""
    during = [] if any(o.startswith("loop_corrections=") for o in overrides) else ["loop_corrections=during"]
    cfg, names = compose_run(["dataset.num_frames=30", "mapper=none", "loop_closure=shifting", "output.progress=false",
                              "checkpoint.save=true", "output.plot=false", *during, *overrides], registry)
    return pipeline.run(cfg, registry, names, out)


def offsets(out: Path) -> np.ndarray:
    """(F,3) estimated minus true camera centres (metres) of a run's frames."""
    _, est = read_tum_trajectory(out / "trajectory.txt")
    _, gt = read_tum_trajectory(out / "groundtruth.txt")
    return est[:, :3, 3] - gt[:, :3, 3]


def check_run_follows_shift(tmp_path: Path, registry, mode: str) -> None:
    """A run with `shifting`: the loop closure moves every keyframe 10 cm along x once: the whole trajectory is then
    10 cm along x of the truth, the frames before the correction (they followed their keyframe)
    and after it (tracked against the moved map, from the moved motion model) alike; keyframes.txt
    and the pose graph agree; the map is the uncorrected run's moved by 10 cm; loops.csv and
    pose_graph.g2o are written. In real time the loop closure sleeps 1.5 s a call in a process
    of its own, and no frame waits for it (each is tracked in less)."""
    log = tmp_path / "calls.txt"
    sleep = ["loop_closure.sleep_s=1.5", "mode=realtime", f"loop_closure.log={log}"] if mode == "realtime" else []
    metrics = run_shifted(registry, tmp_path / "shifted", *sleep)
    run_shifted(registry, tmp_path / "plain", "loop_closure=none", *(["mode=realtime"] if sleep else []))
    shifted = offsets(tmp_path / "shifted")
    assert np.abs(offsets(tmp_path / "plain")).max() < 0.01  # synthetic tracking: millimetres
    np.testing.assert_allclose(shifted, np.tile([0.10, 0.0, 0.0], (len(shifted), 1)), atol=0.01)
    assert metrics["loop_corrections"] == 1 and metrics["loops_accepted"] == 1
    _, keyframes = read_tum_trajectory(tmp_path / "shifted" / "keyframes.txt")
    graph = read_g2o(tmp_path / "shifted" / "pose_graph.g2o")
    np.testing.assert_allclose(graph.poses[:, :3, 3], keyframes[:len(graph.poses), :3, 3], atol=1e-6)
    with open(tmp_path / "shifted" / "loops.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["accepted"] == "True" and rows[0]["fitness"] == "0.9"
    shifted_map, _ = checkpoint.load_map(tmp_path / "shifted")
    plain_map, _ = checkpoint.load_map(tmp_path / "plain")
    shift = shifted_map.entry_means.mean(dim=0) - plain_map.entry_means.mean(dim=0)
    np.testing.assert_allclose(shift.numpy(), [0.10, 0.0, 0.0], atol=0.01)
    if mode == "realtime":
        pids = log.read_text().split()
        assert len(pids) >= 2 and str(os.getpid()) not in pids
        with open(tmp_path / "shifted" / "frames.csv") as f:
            tracking_ms = [float(r["tracking_ms"]) for r in csv.DictReader(f) if r["tracking_ms"]]
        assert len(tracking_ms) == 30 and max(tracking_ms) < 1000, max(tracking_ms)
        assert metrics["loop_closure_wall_s"] >= 1.5 * metrics["loop_closure_calls"] >= 3.0
