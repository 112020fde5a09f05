"""Tracking first in real time: the mapping thread, and every thread that works for it (the
compiled kernels' pools, torch's), run at the lower priority asked for, as Linux reports it in
/proc/self/task/*/stat; and the run reports what held mapping back. The compiled kernels' pools
in a process of their own: tests/e2e/test_scheduling_runs.py."""

from __future__ import annotations

import os
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


@linux_only
def test_the_mapping_thread_runs_at_its_priority_and_says_what_held_it_back():
    from slamkit.run.workers import MappingThread

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
