"""A loop closure in a process of its own (real time), so that its work never holds the tracking
thread up.

A thread is not enough: Python runs one thread's bytecode at a time, and C code that does not
release the GIL (open3d's voxel downsampling, normals and FPFH features, which `pose_graph`
computes for every keyframe; any loop closure written in Python) stops the tracking thread for as
long as it runs, whatever its scheduling priority; at a lower priority it is worse, as the thread
holding the GIL waits for a CPU while tracking waits for it. In a process of its own, at
`realtime.mapping_priority` (its threads, open3d's OpenMP workers included, inherit it), the loop closure
shares nothing with tracking but the CPUs.

`LoopClosureProcess` is a `LoopClosure` that forwards every call to the plugin built in the
child process (`spawn`: a fresh interpreter, no copy of the parent's threads or map) and waits
for its answer; `slamkit.run.workers.LoopThread` is the parent's thread that waits. The
child ignores SIGINT and SIGTERM (the run decides when it stops: it still asks the child for its
graph and its state after a signal), and exits when its pipe closes (the run ended, or died).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import signal
import time
import traceback
from typing import Any

from slamkit.config import PluginConfig, RunContext
from slamkit.roles.loop_closure import LoopCheck, LoopClosure, LoopDecision, LoopKeyframe, PoseGraph
from slamkit.scheduling import ThreadPriority, lower_calling_thread


class LoopClosureError(RuntimeError):
    """The loop closure failed in its process (the child's exception, by name and message)."""


def _serve(conn, cls: type, config: PluginConfig, context: RunContext, priority: ThreadPriority) -> None:
    """The child: build the plugin, then answer (method, args) requests with (ok, value, CPU
    seconds of this process in the call) until the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:  # at normal priority: its imports run beside the run's start-up, not after its stream
        closure = cls(config, context)
        conn.send((True, None, 0.0))
    except Exception as exc:
        conn.send((False, f"{type(exc).__name__}: {exc}", 0.0))
        return
    lower_calling_thread(priority)  # the threads it starts from now on inherit it
    while True:
        try:
            method, args = conn.recv()
        except (EOFError, OSError):
            return
        start = time.process_time()
        try:
            value, ok = getattr(closure, method)(*args), True
        except Exception as exc:
            value, ok = f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}", False
        try:
            conn.send((ok, value, time.process_time() - start))
        except (EOFError, OSError, BrokenPipeError):
            return


class LoopClosureProcess(LoopClosure):
    """The loop closure `cls(config, context)`, run in a child process at `priority` (module
    docstring); `context` reaches it without the shared map and without `build` (neither
    crosses a process). `cpu_s`: the child's CPU seconds in its calls so far, its threads
    included. `close()` ends the child."""

    def __init__(self, cls: type, config: PluginConfig, context: RunContext = RunContext(),
                 priority: ThreadPriority = ThreadPriority.idle):
        self.cls, self.cfg = cls, config
        self.closes_loops = cls.closes_loops
        spawn = multiprocessing.get_context("spawn")
        self._conn, child = spawn.Pipe()
        context = dataclasses.replace(context, gaussian_map=None, build=None)
        self._process = spawn.Process(target=_serve, args=(child, cls, config, context, ThreadPriority(priority)),
                                      name="slamkit-loop-closure", daemon=True)
        self._process.start()
        child.close()
        self.cpu_s = 0.0
        # complete when built: its start-up (imports, seconds) is over before the stream, where it
        # would take the CPU the mapper gets
        ok, why, _ = self._receive()
        if not ok:
            self.close()
            raise LoopClosureError(f"{cls.__name__} could not be built in its process: {why}")

    def _call(self, method: str, *args: Any) -> Any:
        self._conn.send((method, args))
        ok, value, cpu_s = self._receive()
        self.cpu_s += cpu_s
        if not ok:
            raise LoopClosureError(value.splitlines()[0] if value else "failed")
        return value

    def _receive(self) -> tuple[bool, Any, float]:
        try:
            return self._conn.recv()
        except (EOFError, OSError) as exc:
            raise LoopClosureError(f"the loop closure's process ended (exit code {self._process.exitcode})") from exc

    def add_keyframe(self, keyframe: LoopKeyframe) -> None:
        self._call("add_keyframe", keyframe)

    def detect_and_optimise(self) -> LoopDecision:
        return self._call("detect_and_optimise")

    def loops(self) -> list[LoopCheck]:
        return self._call("loops")

    def pose_graph(self) -> PoseGraph:
        return self._call("pose_graph")

    def state_dict(self) -> dict[str, Any]:
        return self._call("state_dict")

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._call("load_state_dict", state)

    def close(self) -> None:
        """End the child process (it exits when its pipe closes)."""
        self._conn.close()
        self._process.join(timeout=10)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
