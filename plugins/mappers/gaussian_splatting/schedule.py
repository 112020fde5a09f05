"""The training schedule of the 3DGS trainer: which keyframe each step trains on (the untrained
ones first, once each, then the sampler's choice), at which resolution (`coarse_steps` at half
size first), and which window of it (`window`), all random draws from one seeded generator so
that a run and its resume draw the same."""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import torch

from slamkit.roles.sampler import KeyframeSampler
from slamkit.roles.training_view import TrainingView
from slamkit_plugins.mappers.gaussian_splatting.keyframes import KeyframeStore

#: Pixels: a training window's smallest side (the loss's SSIM takes 11x11 windows; a tile is 16).
MIN_WINDOW_SIDE = 16


class TrainingSchedule:
    """Each step's training view from `keyframes`: coarse_steps (half-size steps a keyframe
    takes first), window (fraction of the view's width and height a step trains on; 1: the whole
    view), seed (of the sampler's draws and the windows)."""

    def __init__(self, keyframes: KeyframeStore, sampler: KeyframeSampler, coarse_steps: int, window: float,
                 seed: int):
        self.keyframes, self.sampler, self.coarse_steps, self.window = keyframes, sampler, coarse_steps, window
        self.pending: deque[int] = deque()  # keyframes not trained on yet
        self.trained: dict[int, int] = {}  # steps taken on each keyframe
        self.rng = np.random.default_rng(seed)

    def add(self, keyframe_id: int) -> None:
        """A new keyframe: trained on before any sampled one."""
        self.pending.append(keyframe_id)

    def next_view(self, device: torch.device) -> TrainingView:
        """The next step's view, on `device`."""
        kf_id = self.pending.popleft() if self.pending else self._sample()
        coarse = self.trained.get(kf_id, 0) < self.coarse_steps
        self.trained[kf_id] = self.trained.get(kf_id, 0) + 1
        return self._window(self.keyframes.view(kf_id, device, 0.5 if coarse else 1.0))

    def state_dict(self) -> dict[str, Any]:
        """pending, steps per keyframe, the generator's state (copies: call under the map's lock
        while a mapping thread trains)."""
        pending, trained = self.pending.copy(), dict(self.trained)
        return {"pending": list(pending), "trained": [[k, v] for k, v in trained.items()],
                "rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pending = deque(int(k) for k in state["pending"])
        self.trained = {int(k): int(v) for k, v in state["trained"]}
        self.rng.bit_generator.state = state["rng"]

    def _window(self, view: TrainingView) -> TrainingView:
        """A random window of `view` of the configured size (`window`, at least MIN_WINDOW_SIDE
        pixels a side), or the view itself. A window may start up to its size (less
        MIN_WINDOW_SIDE) before the view's edge and is clipped to the view, so border pixels are
        trained about as often as the others (a window drawn inside the view would rarely hold
        them)."""
        if self.window >= 1.0:
            return view
        spans = []
        for size in (view.camera.width, view.camera.height):
            part = min(size, max(MIN_WINDOW_SIDE, round(size * self.window)))
            reach = part - MIN_WINDOW_SIDE if part < size else 0
            start = int(self.rng.integers(-reach, size - part + reach + 1))
            spans.append((max(start, 0), min(start + part, size) - max(start, 0)))
        (x0, width), (y0, height) = spans
        return view.window(x0, y0, width, height)

    def _sample(self) -> int:
        ids = list(self.keyframes.ids)
        return self.sampler.sample(ids, {k: self.keyframes[k].pose for k in ids}, self.rng)
