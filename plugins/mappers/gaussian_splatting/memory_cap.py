"""The memory cap: a bound on the number of Gaussians in the map, enforced by pruning the least
opaque ones whatever the strategy."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import torch

from slamkit.config import PluginConfig, require
from slamkit.roles.map_edit import MapEdit

log = logging.getLogger(__name__)


@dataclass
class MemoryCapConfig(PluginConfig):
    """A bound on the map's size (what a Gaussian costs: docs/results.md, "The memory guard")."""

    #: the most Gaussians the map may hold (null: unlimited, the paper's behaviour)
    max_gaussians: int | None = None
    #: when the cap prunes, it frees this fraction of max_gaussians below it (so it does not prune every keyframe)
    margin: float = 0.1

    def validate(self) -> None:
        require(self.max_gaussians is None or self.max_gaussians > 0, "mapper.memory_cap.max_gaussians",
                "null (unlimited) or an integer > 0", self.max_gaussians)
        require(0 <= self.margin < 1, "mapper.memory_cap.margin", "in [0, 1)", self.margin)


class MemoryCap:
    """Prunes the least opaque Gaussians when the map holds more than `max_gaussians`."""

    def __init__(self, cfg: MemoryCapConfig):
        self.cfg = cfg
        self.pruned = 0  # Gaussians removed
        self.prunings = 0  # times it pruned

    def enforce(self, edit: MapEdit, protect: slice | None = None) -> int:
        """When the map holds more than max_gaussians, remove the least opaque Gaussians (ties:
        older rows first) until floor((1 - margin) max_gaussians) remain; rows in `protect` (a
        keyframe's new Gaussians, whose opacity is still the initial value and says nothing yet)
        go only when the others do not make room. Returns the number removed."""
        cap, n = self.cfg.max_gaussians, len(edit)
        if cap is None or n <= cap:
            return 0
        excess = n - max(1, int(cap * (1.0 - self.cfg.margin)))
        key = torch.nan_to_num(edit.params["opacity_logits"].clone(), nan=-math.inf)
        if protect is not None:
            key[protect] = math.inf
        drop = torch.zeros(n, dtype=torch.bool, device=key.device)
        drop[torch.sort(key, stable=True).indices[:excess]] = True
        edit.remove(drop)
        self.pruned += excess
        self.prunings += 1
        log.debug("memory cap: pruned the %d least opaque Gaussians, %d left", excess, len(edit))
        return excess

    def metrics(self) -> dict[str, Any]:
        return {"pruned_by_memory_cap": self.pruned, "memory_cap_prunings": self.prunings}
