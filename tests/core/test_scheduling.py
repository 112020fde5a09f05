"""Tracking first in real time: the mapping thread, and every thread that works for it (the
compiled kernels' pools, torch's), run at the lower priority asked for, as Linux reports it in
/proc/self/task/*/stat; and the run reports what held mapping back."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading

import pytest

from slamkit.scheduling import LOW_NICE_STEPS, ThreadPriority, lower_calling_thread, process_threads, thread_schedule

linux_only = pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="per-thread priorities are Linux's")


def _in_thread(priority: ThreadPriority):
    seen = {}

    def body():
        seen["lowered"] = lower_calling_thread(priority)
        seen["schedule"] = thread_schedule()

    t = threading.Thread(target=body)
    t.start()
    t.join()
    return seen


@linux_only
@pytest.mark.parametrize("priority, policy, nice_steps", [(ThreadPriority.idle, "idle", 0),
                                                          (ThreadPriority.low, "normal", LOW_NICE_STEPS),
                                                          (ThreadPriority.same, "normal", 0)])
def test_a_thread_lowers_its_own_priority_only(priority, policy, nice_steps):
    main = thread_schedule()
    seen = _in_thread(priority)
    assert seen["lowered"]
    assert seen["schedule"].policy == policy and seen["schedule"].nice == main.nice + nice_steps
    after = thread_schedule()  # the calling thread's is untouched
    assert (after.policy, after.nice) == (main.policy, main.nice)


# A fresh process: the kernels' pools (one set of workers per caller's priority) are per process.
POOL_SCRIPT = textwrap.dedent("""
    import json, sys, threading
    from slamkit.run.build import build_run
    from slamkit.scheduling import lower_calling_thread, process_threads, ThreadPriority
    import torch
    torch.set_num_threads(2)
    dataset, slam, _ = build_run(["dataset=synthetic", "dataset.num_frames=4", "dataset.width=160",
        "dataset.height=120", "keyframe=every_n", "mapper=gaussian_splatting", "mapper/rasterizer=cpu",
        "mapper.rasterizer.num_threads=2", "mapper.loss.num_threads=2", "mode=realtime"])
    slam.initialize(dataset[0].gt_pose)
    for i in range(len(dataset)):
        slam.track(dataset[i])
    assert slam.optimize(2) == 2  # the main thread first: the pools' workers at normal priority
    before = {t.tid: t for t in process_threads()}
    def mapping():
        assert lower_calling_thread(ThreadPriority(sys.argv[1]))
        assert slam.optimize(3) == 3
    t = threading.Thread(target=mapping)
    t.start()
    t.join()
    after = process_threads()
    main = min(before)
    print(json.dumps({"main": [before[main].policy, before[main].nice],
                      "old": [[t.policy, t.nice, t.cpu_s - before[t.tid].cpu_s] for t in after
                              if t.tid in before and t.tid != main],
                      "new": [[t.policy, t.nice, t.cpu_s] for t in after if t.tid not in before]}))
""")


@linux_only
@pytest.mark.parametrize("priority, expected", [("idle", ["idle", 0]), ("low", ["normal", LOW_NICE_STEPS])])
def test_the_kernels_workers_of_a_mapping_step_run_at_the_mapping_threads_priority(tmp_path, priority, expected):
    """The main thread trains first, starting the rasteriser's and the loss's pools at normal
    priority; a thread at a lower priority then trains: its jobs get workers of their own (new
    threads, at its priority), and the main thread's stay as they were."""
    env = {**os.environ, "SLAMKIT_CACHE": os.environ.get("SLAMKIT_CACHE", str(tmp_path / "cache"))}
    proc = subprocess.run([sys.executable, "-c", POOL_SCRIPT, priority], capture_output=True, text=True, env=env,
                          timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    import json

    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    # the normal-priority workers did none of its work (a thread woken for nothing runs microseconds)
    assert all(t[:2] == seen["main"] and t[2] < 1e-3 for t in seen["old"]), seen
    assert seen["new"], "the lowered thread's jobs started no workers of its own"
    expected[1] += seen["main"][1]
    assert all(t[:2] == expected for t in seen["new"]), seen


@linux_only
def test_the_mapping_thread_runs_at_its_priority_and_says_what_held_it_back():
    from slamkit.run.slam import MappingThread

    class Mapper:
        def __init__(self):
            self.calls, self.schedule = 0, None

        def optimize(self, steps):
            self.calls += 1
            self.schedule = thread_schedule()
            return 0 if self.calls <= 3 else steps  # three waits for a keyframe first

    mapper = Mapper()
    main = thread_schedule()
    thread = MappingThread(mapper, switch_interval_s=5e-4, priority=ThreadPriority.low)
    thread.start()
    while thread.iterations < 5:
        thread.check()
        threading.Event().wait(0.01)
    thread.stop()
    assert mapper.schedule.nice == main.nice + LOW_NICE_STEPS
    throttle = thread.throttle
    assert throttle.priority == "low" and throttle.no_keyframe_s >= 3 * 0.005
    assert throttle.cpu_wait_s >= 0 and throttle.blocked_s >= 0
    assert thread_schedule().nice == main.nice  # the tracking thread's is unchanged


def test_process_threads_lists_the_calling_thread():
    threads = process_threads()
    if not os.path.isdir("/proc/self/task"):
        assert threads == []
        return
    me = thread_schedule()
    assert me.tid in {t.tid for t in threads} and me.cpu_s > 0
