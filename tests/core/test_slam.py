"""The SLAM loop with the G-ICP tracker and the `none` mapper (tracking only)."""

from __future__ import annotations

import numpy as np

from slamkit.run.build import build_run


def _run(keep_untrackable: bool, frames: int = 30):
    dataset, slam, _ = build_run(["dataset=synthetic", f"dataset.num_frames={frames}", "tracker=gicp",
                                  "keyframe=overlap", "mapper=none", f"mapper.keep_untrackable={keep_untrackable}"])
    slam.initialize(dataset[0].gt_pose)
    poses = [slam.step(dataset[i]).tracking.pose for i in range(len(dataset))]
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

    from slamkit.run.slam import MappingThread

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
