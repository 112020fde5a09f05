"""Where a training step's time goes: wall and thread CPU time per phase, summed over steps."""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

#: The phases of a training step, in order (`lock`: waiting for the map's lock).
PHASES = ("view", "render", "loss", "backward", "lock", "optimizer", "strategy")


class PhaseTimer:
    """Accumulates seconds per phase: `with timer("render"): ...`. Wall time is what the step
    took; thread CPU time is what this thread computed (the rest was waiting, or other
    threads: the compiled rasteriser's workers are not counted)."""

    def __init__(self):
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.steps = 0
        self.sync = None  # e.g. torch.cuda.synchronize: a GPU's queued work is charged to its phase

    @contextmanager
    def __call__(self, phase: str):
        wall, cpu = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            if self.sync is not None:
                self.sync()
            self.wall[phase] += time.perf_counter() - wall
            self.cpu[phase] += time.thread_time() - cpu

    def per_step_ms(self) -> dict[str, float]:
        """Mean wall milliseconds per step, by phase, and their total (`step`)."""
        n = max(self.steps, 1)
        out = {p: 1e3 * self.wall[p] / n for p in PHASES if p in self.wall}
        out["step"] = sum(out.values())
        return out

    def reset(self) -> None:
        self.wall.clear()
        self.cpu.clear()
        self.steps = 0
