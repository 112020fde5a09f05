"""The SLAM loop with the G-ICP tracker: tracking only (the `none` mapper), the real-time
threads (mapping beside tracking, keyframes handed over beside it)."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.errors import PluginError
from slamkit.run.build import build_run
from slamkit.types import KeyframeKind


def _run(keep_untrackable: bool, frames: int = 30):
    dataset, slam, _ = build_run(["dataset=synthetic", f"dataset.num_frames={frames}", "tracker=gicp",
                                  "keyframe=overlap", "mapper=none", f"mapper.keep_untrackable={keep_untrackable}"])
    slam.initialize(dataset[0].gt_pose)
    poses = [slam.process(dataset[i]).tracking.pose for i in range(len(dataset))]
    return np.array(poses), slam


def test_tracking_only_map_keeps_only_trackable_gaussians_without_changing_tracking():
    lean_poses, lean = _run(keep_untrackable=False)
    full_poses, full = _run(keep_untrackable=True)
    assert lean.num_keyframes == full.num_keyframes >= 2
    assert bool(lean.gaussian_map.trackable.all())
    assert len(lean.gaussian_map) < 0.8 * len(full.gaussian_map)
    np.testing.assert_allclose(lean_poses, full_poses, atol=1e-9)  # the target is the same


def test_mapping_threads_leave_one_cpu_to_the_tracker_in_realtime_mode(monkeypatch):
    import torch

    from slamkit.registry.schema import Mode, RunConfig
    from slamkit.run.pipeline import mapping_threads

    monkeypatch.setattr(torch, "get_num_threads", lambda: 4)
    assert mapping_threads(RunConfig(mode=Mode.sequential)) == 4
    assert mapping_threads(RunConfig(mode=Mode.realtime)) == 3
    assert mapping_threads(RunConfig(mode=Mode.realtime, mapping_threads=2)) == 2
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert mapping_threads(RunConfig(mode=Mode.realtime)) == 1


def test_tracking_threads_default_to_one_in_realtime_mode(monkeypatch):
    from slamkit.registry.schema import Mode, RunConfig
    from slamkit.run.build import tracking_threads

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert tracking_threads(RunConfig(mode=Mode.sequential)) == 3
    assert tracking_threads(RunConfig(mode=Mode.realtime)) == 1


def test_the_mapping_thread_shortens_the_gil_switch_interval_while_it_runs():
    """The mapping thread's torch calls and the tracker's Python code take turns on the GIL:
    while the thread runs, the interval is the one asked for, and stop() restores Python's."""
    import sys
    import threading

    from slamkit.run.workers import MappingThread

    class Recorder:
        def __init__(self):
            self.seen, self.ran = [], threading.Event()

        def optimize(self, steps):
            self.seen.append(sys.getswitchinterval())
            self.ran.set()
            return steps

    before = sys.getswitchinterval()
    mapper = Recorder()
    thread = MappingThread(mapper, switch_interval_s=2e-4)
    thread.start()
    assert mapper.ran.wait(10)
    thread.stop()
    assert mapper.seen and all(abs(s - 2e-4) < 1e-9 for s in mapper.seen)
    assert sys.getswitchinterval() == before


def _keyframe_run(defer: bool, frames: int = 12):
    """A synthetic run with tracking and mapping-only keyframes, each frame tracked with
    `slam.process` of a SLAM built for real time, the keyframes' work beside tracking or not
    (`realtime.keyframe_thread`); the
    mapper's `add_keyframe` made slow (30 ms) and every call of `admit` / `add_keyframe` logged
    with its start and end, so that an overlap would show."""
    import time

    dataset, slam, _ = build_run(["dataset=synthetic", f"dataset.num_frames={frames}", "dataset.width=64",
                                  "dataset.height=48", "tracker=gicp", "keyframe=every_n", "keyframe.tracking_every=4",
                                  "keyframe.mapping_every=2", "mapper=gaussian_splatting", "mode=realtime",
                                  f"realtime.keyframe_thread={defer}"])
    calls = []

    def logged(name, method, pause=0.0):
        def call(*args, **kwargs):
            calls.append((name, "start"))
            time.sleep(pause)
            try:
                return method(*args, **kwargs)
            finally:
                calls.append((name, "end"))
        return call

    slam.mapper.admit = logged("admit", slam.mapper.admit)
    slam.mapper.add_keyframe = logged("add_keyframe", slam.mapper.add_keyframe, pause=0.03)
    slam.initialize(dataset[0].gt_pose)
    steps = [slam.process(dataset[i]) for i in range(len(dataset))]
    slam.settle()
    return slam, steps, calls


def _rows(slam) -> np.ndarray:
    """The map's rows (keyframe, trackable, means) in one order, whatever order they entered in."""
    gm = slam.gaussian_map
    rows = np.column_stack([gm.keyframe_id.numpy(), gm.trackable.numpy(), gm.means.detach().numpy()])
    return rows[np.lexsort(rows.T[::-1])]


def test_keyframes_handed_over_beside_tracking_give_the_same_run():
    """The handover thread takes only what the next frames' tracking does not need: the poses,
    the keyframes and the map are those of the run that waits for every keyframe, and the
    mapper's calls never overlap (each keyframe's `add_keyframe` ends before the next `admit`)."""
    waited, waited_steps, waited_calls = _keyframe_run(defer=False)
    beside, beside_steps, beside_calls = _keyframe_run(defer=True)
    assert beside_calls == waited_calls == [(name, edge) for name in ("admit", "add_keyframe")
                                            for edge in ("start", "end")] * beside.num_keyframes
    kinds = [s.keyframe for s in beside_steps]
    assert KeyframeKind.TRACKING in kinds and KeyframeKind.MAPPING_ONLY in kinds
    assert kinds == [s.keyframe for s in waited_steps]
    np.testing.assert_array_equal([s.tracking.pose for s in beside_steps], [s.tracking.pose for s in waited_steps])
    assert beside.num_keyframes == waited.num_keyframes
    # the same rows; a tracking keyframe's trackable ones enter first beside tracking (the tracker's
    # next target), the rest after the mapper's admission in the handover thread
    np.testing.assert_array_equal(_rows(beside), _rows(waited))
    assert beside.handovers.time_s > 0 and waited.handovers is None
    assert beside.optimize(2) == waited.optimize(2) == 2  # the mapper has every keyframe to train on


def test_the_next_target_is_built_beside_tracking_and_the_next_frame_aligns_to_it():
    """A tracking keyframe's new target is built in the keyframe's thread, not on the tracking
    thread (its frame's pose is not held up by it), and the next frame's alignment starts only
    once it is built (made slow here: 30 ms)."""
    import threading
    import time

    dataset, slam, _ = build_run(["dataset=synthetic", "dataset.num_frames=10", "dataset.width=64",
                                  "dataset.height=48", "tracker=gicp", "keyframe=every_n", "keyframe.tracking_every=3",
                                  "mapper=gaussian_splatting", "mode=realtime", "realtime.keyframe_thread=true"])
    calls = []

    def logged(name, method, pause=0.0):
        def call(*args, **kwargs):
            calls.append((name, "start", threading.current_thread().name))
            time.sleep(pause)
            try:
                return method(*args, **kwargs)
            finally:
                calls.append((name, "end", threading.current_thread().name))
        return call

    slam.tracker.update_target = logged("update_target", slam.tracker.update_target, pause=0.03)
    slam.tracker.track = logged("track", slam.tracker.track)
    slam.initialize(dataset[0].gt_pose)
    for i in range(len(dataset)):
        slam.process(dataset[i])
    slam.settle()
    assert sum(c[:2] == ("update_target", "end") for c in calls) >= 3
    assert {c[2] for c in calls if c[0] == "update_target"} == {"slamkit-keyframe"}
    assert {c[2] for c in calls if c[0] == "track"} == {threading.current_thread().name}
    building = False
    for name, edge, _ in calls:  # no alignment starts while a target is being built
        if name == "update_target":
            building = edge == "start"
        assert not (building and name == "track"), calls


def test_a_failure_beside_tracking_is_raised_on_the_tracking_thread_naming_the_plugin(monkeypatch):
    dataset, slam, _ = build_run(["dataset=synthetic", "dataset.num_frames=3", "dataset.width=64",
                                  "dataset.height=48", "tracker=gicp", "mapper=gaussian_splatting", "mode=realtime"])

    def broken(*args, **kwargs):
        raise RuntimeError("no room for the view")

    monkeypatch.setattr(slam.mapper, "add_keyframe", broken)
    slam.initialize(dataset[0].gt_pose)
    step = slam.process(dataset[0])  # returns before the mapper has it
    assert step.keyframe is KeyframeKind.TRACKING
    with pytest.raises(PluginError, match=r"^mapper plugin 'gaussian_splatting' failed in add_keyframe\(\): "
                                          r"RuntimeError: no room for the view$"):
        slam.settle()
    slam.settle()  # raised once


def test_mapping_starts_no_step_while_tracking_is_late():
    """Past the tracker's deadline (its next frame has arrived) the mapping thread waits
    between steps, and counts the wait; it trains again once tracking is on time."""
    import threading
    import time

    from slamkit.run.workers import MappingThread
    from slamkit.scheduling import ThreadPriority

    class Recorder:
        def __init__(self):
            self.steps, self.ran = 0, threading.Event()

        def optimize(self, steps):
            self.steps += steps
            self.ran.set()
            time.sleep(0.001)
            return steps

    mapper = Recorder()
    # at the tracker's priority: an idle thread may not run at all on a busy machine
    thread = MappingThread(mapper, switch_interval_s=1e-3, priority=ThreadPriority.same)
    thread.yield_to_tracking(time.perf_counter() - 1.0)  # late since a second
    thread.start()
    time.sleep(0.1)
    late_steps = mapper.steps
    thread.yield_to_tracking(None)
    assert mapper.ran.wait(10)
    thread.stop()
    assert late_steps == 0 and mapper.steps > 0
    assert thread.throttle.yielded_s >= 0.05


def test_one_frame_goes_pipeline_runner_slam_then_the_roles_in_order(tmp_path):
    """The first frame of a run, followed through its calls: the pipeline hands it to the
    runner, the runner to `SLAM.process`, which tracks it, decides on a keyframe, grows the map
    (the mapper's admission), hands the keyframe to the mapper, then trains (sequential mode)."""
    from slamkit.registry.compose import compose_run
    from slamkit.registry.discovery import default_registry
    from slamkit.run.lifecycle import StopSignals
    from slamkit.run.pipeline import Pipeline

    registry = default_registry()
    cfg, names = compose_run(["dataset=synthetic", "dataset.num_frames=2", "dataset.width=64", "dataset.height=48",
                              "mapper=gaussian_splatting", "final_iterations=0", "output.progress=false",
                              "output.plot=false"], registry)
    pipeline = Pipeline(cfg, registry, names, tmp_path, StopSignals())
    calls = []

    def logged(owner, attribute, name):
        method = getattr(owner, attribute)

        def call(*args, **kwargs):
            calls.append(name)
            return method(*args, **kwargs)
        setattr(owner, attribute, call)

    slam = pipeline.slam
    logged(pipeline.runner, "process", "runner")
    logged(slam, "process", "slam")
    logged(slam.tracker, "track", "tracker.track")
    logged(slam.keyframe_policy, "decide", "keyframe.decide")
    logged(slam.mapper, "admit", "mapper.admit")
    logged(slam.mapper, "add_keyframe", "mapper.add_keyframe")
    logged(slam.mapper, "optimize", "mapper.optimize")
    with StopSignals().installed():
        pipeline.run()
    first = calls[:calls.index("mapper.optimize") + 1]
    assert first == ["runner", "slam", "tracker.track", "keyframe.decide", "mapper.admit", "mapper.add_keyframe",
                     "mapper.optimize"]
