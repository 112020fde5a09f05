"""`mapper=none`: no map optimisation (tracking only). Keyframe Gaussians still enter the
shared GaussianMap (the pipeline adds them), so a Gaussian-map tracker tracks frame-to-model."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Mapper, PluginConfig


@dataclass
class NoMapperConfig(PluginConfig):
    """No options."""


class NoMapper(Mapper):
    def __init__(self, cfg: NoMapperConfig):
        self.cfg = cfg

    def add_keyframe(self, frame, result, kind, new_rows) -> None:
        pass

    def optimize(self, iterations: int) -> int:
        return 0


@hookimpl
def slamkit_mappers():
    return [PluginSpec("none", NoMapper, NoMapperConfig)]
