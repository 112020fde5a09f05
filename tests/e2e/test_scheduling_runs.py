"""Tracking first in real time, in a fresh process (the compiled kernels' pools, one set of
workers per caller's priority, are per process): a mapping step's kernel workers run at the
priority of the thread that asked for them, as Linux reports it in /proc/self/task/*/stat. The
scheduling itself: tests/core/test_scheduling.py."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from slamkit.scheduling import LOW_NICE_STEPS

linux_only = pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="per-thread priorities are Linux's")


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
        slam.process(dataset[i])
    slam.settle()  # the keyframes handed over beside tracking are the mapper's
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
    # OMP_WAIT_POLICY: torch's OpenMP workers sleep at once after their last region instead of
    # spinning (libgomp's spin count), which ran into the count as 1.7 ms of an old thread's CPU
    env = {**os.environ, "SLAMKIT_CACHE": os.environ.get("SLAMKIT_CACHE", str(tmp_path / "cache")),
           "OMP_WAIT_POLICY": "passive"}
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
