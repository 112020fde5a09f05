"""`mapper=none`: no map optimisation (tracking only).

Keyframe Gaussians still enter the shared GaussianMap, so a Gaussian-map tracker tracks
frame-to-model. Since nothing renders the map, only the trackable ones are admitted (the others
overlap the map or lie beyond depth_trunc): the map then grows with new surface only, not with
every keyframe's pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Mapper, PluginConfig


@dataclass
class NoMapperConfig(PluginConfig):
    """Tracking only."""

    #: admit the keyframe Gaussians that tracking does not use too (as a 3DGS mapper would); false saves memory
    keep_untrackable: bool = False


class NoMapper(Mapper):
    """Admits a keyframe's trackable Gaussians; trains nothing."""

    grows_from_frames = False  # nothing renders the map: a tracker without Gaussians needs none made

    def admit(self, frame, pose, new):
        return None if self.cfg.keep_untrackable else new.trackable

    def add_keyframe(self, frame, pose, kind, new_rows) -> None:
        pass

    def optimize(self, iterations: int) -> int:
        return 0


@hookimpl
def slamkit_plugins():
    return [PluginSpec("none", NoMapper, NoMapperConfig)]
