"""One training step of the `gaussian_splatting` mapper, timed by phase: render, loss, backward,
optimizer (the update, the colour clamp), strategy (the post-backward hook: statistics,
densification, pruning on its schedule).

A self-contained stand-in for a step profiler in the mapper itself: `timed_step` takes the same
step as `GaussianSplattingMapper.train_step`, without its real-time checks (no other thread may
change the map meanwhile). Used by benchmarks/gpu_bench.py and tests/test_cuda.py:

    clock = PhaseClock(torch.cuda.synchronize)
    loss = timed_step(mapper, mapper.keyframes[kf_id].view("cuda"), clock)
    clock.seconds   # {"render": ..., "loss": ..., ...}, summed over the steps timed
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager

import torch

from slamkit.roles import StepInfo

PHASES = ("render", "loss", "backward", "optimizer", "strategy")


class PhaseClock:
    """Wall-clock seconds per phase, summed over the steps timed. `sync` (None: nothing) runs
    before each reading, e.g. torch.cuda.synchronize, so that a phase is charged with the GPU
    work it launched rather than with the launches alone."""

    def __init__(self, sync: Callable[[], None] | None = None):
        self.sync = sync or (lambda: None)
        self.seconds = {name: 0.0 for name in PHASES}
        self.steps = 0

    @contextmanager
    def __call__(self, phase: str):
        self.sync()
        start = time.perf_counter()
        yield
        self.sync()
        self.seconds[phase] += time.perf_counter() - start

    def per_step_ms(self) -> dict[str, float]:
        """Milliseconds per step for each phase and their sum (`step`)."""
        ms = {name: 1e3 * s / max(self.steps, 1) for name, s in self.seconds.items()}
        ms["step"] = sum(ms.values())
        return ms


def unwrapped(plugin):
    """The plugin itself where `slamkit.run.pipeline` wrapped it (Blamed), else `plugin`."""
    return getattr(plugin, "_plugin", plugin)


def timed_step(mapper, view, clock: PhaseClock) -> float:
    """One step of `mapper` (a GaussianSplattingMapper, bound to its map; a pipeline's wrapped
    mapper is unwrapped) on `view` (a TrainingView on the map's device), each phase timed by
    `clock`; returns the loss."""
    mapper = unwrapped(mapper)
    gm = mapper.gaussian_map
    with gm.lock:
        params = gm.parameters()
    with clock("render"):
        render = mapper.render(view.world_to_camera, view.camera, params)
    with clock("loss"):
        loss = mapper.loss(render, view)
    with clock("backward"):
        names = list(params)
        grads = torch.autograd.grad(loss, [params[k] for k in names], allow_unused=True)
        grads = {k: g for k, g in zip(names, grads) if g is not None}
    value = float(loss.detach())
    with gm.lock:
        with clock("optimizer"):
            mapper.edit.sync()
            mapper.optimizer.step(params, grads)
            with torch.no_grad():
                params["colors"].clamp_(0.0, 1.0)
            gm.version += 1
            mapper.steps += 1
        with clock("strategy"):
            mapper.strategy.step_post_backward(mapper.edit, StepInfo(mapper.steps, view, render, grads, value))
    clock.steps += 1
    return value
