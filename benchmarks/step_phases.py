"""Mapping steps timed by phase on a GPU: the mapper's own PhaseTimer (phases view, render, loss,
backward, lock, optimizer, strategy; `plugins/mappers/gaussian_splatting/timing.py`) with a
synchronisation before and after each phase, so that a phase is charged with the GPU work it
launched rather than with the launches alone (CUDA kernels run asynchronously: without it, the
render's time shows up in whichever later phase first waits for a result).

Used by benchmarks/gpu_bench.py and tests/e2e/test_cuda.py:

    timer = time_steps(slam.mapper, 10, torch.cuda.synchronize)   # the mapper's own steps
    timer.per_step_ms()   # {"view": ..., "render": ..., ..., "step": ...}
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import contextmanager

from slamkit_plugins.mappers.gaussian_splatting.timing import PhaseTimer

#: The phases every timed step goes through (view: only when the mapper picks the keyframe;
#: lock: waiting for the map's lock).
STEP_PHASES = ("render", "loss", "backward", "optimizer", "strategy")


class SyncedPhaseTimer(PhaseTimer):
    """PhaseTimer that calls `sync` (e.g. torch.cuda.synchronize; None: nothing) on entering and
    before leaving each phase."""

    def __init__(self, sync: Callable[[], None] | None = None):
        super().__init__()
        self.sync = sync or (lambda: None)

    @contextmanager
    def __call__(self, phase: str):
        self.sync()
        with super().__call__(phase):
            yield
            self.sync()


def time_steps(mapper, steps: int, sync: Callable[[], None] | None = None, view=None) -> SyncedPhaseTimer:
    """`steps` training steps of `mapper` (a GaussianSplattingMapper), timed by phase with `sync`
    around each phase: the mapper's own `optimize` (it picks the keyframes), or its trainer's
    `step(view)` on one TrainingView when `view` is given. The trainer's timer is restored
    afterwards; returns the one that timed them."""
    saved, timer = mapper.timer, SyncedPhaseTimer(sync)
    mapper.timer = timer
    try:
        if view is None:
            mapper.optimize(steps)
        else:
            for _ in range(steps):
                mapper.step(view)
                timer.steps += 1
    finally:
        mapper.timer = saved
    return timer
