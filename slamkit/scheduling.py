"""Scheduling priority of the real-time mapping thread, and what the OS says about a thread's
scheduling (Linux /proc): its class, its CPU time and its time waiting for a CPU.

In real time the tracker paces the system, so the mapping thread runs at a lower priority
(`ThreadPriority`); on Linux a thread's priority is its own and the threads it starts inherit it,
and the compiled kernels' persistent pools keep one set of workers per caller's priority
(slamkit/csrc/slk_thread_pool.h), so everything the mapper runs is at its priority. Elsewhere, or
where the OS refuses, nothing changes (`lower_calling_thread` says so).
"""

from __future__ import annotations

import enum
import os
import threading
from dataclasses import dataclass
from pathlib import Path


class ThreadPriority(enum.Enum):
    """idle: the thread runs only on CPU time that no thread of normal priority wants (Linux
    SCHED_IDLE). low: LOW_NICE_STEPS nice levels below its starter (a share of a contended core,
    about a third of a normal thread's at 5 steps). same: as its starter."""

    idle = "idle"
    low = "low"
    same = "same"


#: Nice steps of `ThreadPriority.low` (Linux nice levels; each is ~1.25x less CPU share).
LOW_NICE_STEPS = 5

_POLICIES = {0: "normal", 3: "batch", 5: "idle"}  # Linux SCHED_OTHER, SCHED_BATCH, SCHED_IDLE


def lower_calling_thread(priority: ThreadPriority) -> bool:
    """Lower the calling thread's scheduling priority as `priority` says (threads it starts
    from now on inherit it). True where it took effect (or nothing was asked); False where the
    OS has no per-thread priority or refused."""
    priority = ThreadPriority(priority)
    if priority is ThreadPriority.same:
        return True
    try:
        tid = threading.get_native_id()
        if priority is ThreadPriority.idle:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        else:
            os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + LOW_NICE_STEPS)
        return True
    except (AttributeError, OSError):
        return False


@dataclass(frozen=True)
class ThreadSchedule:
    """One thread as the OS schedules it: its policy (normal, batch, idle), nice value, CPU
    seconds it ran, seconds it was runnable but waited for a CPU, and its name."""

    tid: int
    name: str
    policy: str
    nice: int
    cpu_s: float
    cpu_wait_s: float


def thread_schedule(tid: int | None = None) -> ThreadSchedule | None:
    """What Linux says about thread `tid` of this process (None: the calling thread); None where
    /proc does not tell (another OS, a thread that has ended)."""
    tid = threading.get_native_id() if tid is None else tid
    task = Path(f"/proc/self/task/{tid}")
    try:
        stat = (task / "stat").read_text()
        run_ns, wait_ns = (task / "schedstat").read_text().split()[:2]
    except (OSError, ValueError):
        return None
    name = stat[stat.index("(") + 1:stat.rindex(")")]
    fields = stat[stat.rindex(")") + 2:].split()  # from field 3 (state) on
    nice, policy = int(fields[19 - 3]), int(fields[41 - 3])
    return ThreadSchedule(tid, name, _POLICIES.get(policy, str(policy)), nice, int(run_ns) / 1e9, int(wait_ns) / 1e9)


def process_threads() -> list[ThreadSchedule]:
    """Every thread of this process that /proc lists (empty elsewhere)."""
    try:
        tids = sorted(int(p.name) for p in Path("/proc/self/task").iterdir())
    except OSError:
        return []
    return [s for s in map(thread_schedule, tids) if s is not None]
