"""`mapper=none`: no map optimisation (tracking only).

Keyframe Gaussians still enter the shared GaussianMap (the pipeline adds them), so a
Gaussian-map tracker tracks frame-to-model. Since nothing renders the map, the new Gaussians
that are not trackable (they overlap the map, or lie beyond depth_trunc) are removed again at
once: the map then grows with new surface only, not with every keyframe's pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Mapper, PluginConfig


@dataclass
class NoMapperConfig(PluginConfig):
    """keep_untrackable: keep the keyframe Gaussians that tracking does not use (as a 3DGS mapper
    would, for rendering); false saves memory."""

    keep_untrackable: bool = False


class NoMapper(Mapper):
    def __init__(self, cfg: NoMapperConfig):
        self.cfg = cfg

    def add_keyframe(self, frame, result, kind, new_rows) -> None:
        if self.cfg.keep_untrackable or new_rows.stop == new_rows.start:
            return
        keep = torch.ones(len(self.gaussian_map), dtype=torch.bool)
        keep[new_rows] = self.gaussian_map.trackable[new_rows]
        if not bool(keep.all()):
            self.gaussian_map.keep(keep)

    def optimize(self, iterations: int) -> int:
        return 0


@hookimpl
def slamkit_mappers():
    return [PluginSpec("none", NoMapper, NoMapperConfig)]
