"""The training-view sampler part: which keyframe a training step uses."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Mapping

import numpy as np


class KeyframeSampler(ABC):
    """Chooses which keyframe the trainer trains on next (after every new keyframe was trained
    on once: the trainer takes those first)."""

    @abstractmethod
    def sample(self, keyframe_ids: list[int], keyframe_poses: Mapping[int, np.ndarray],
               rng: np.random.Generator) -> int:
        """One of `keyframe_ids` (non-empty, in arrival order: the last is the newest).
        keyframe_poses: id -> (4,4) camera-to-world pose; a sampler that needs no geometry
        ignores it. rng: the trainer's generator (the run's draws are reproducible)."""
