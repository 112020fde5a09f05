"""`keyframe=every_n`: fixed-interval keyframes (the paper's baseline in Fig. 4a).

A tracking keyframe every `tracking_every` frames (the first frame included), and a
mapping-only keyframe every `mapping_every` frames after the last keyframe (0 = none).
"""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import (
    KeyframeDecision,
    KeyframeHistory,
    KeyframePolicy,
    PluginConfig,
    RunContext,
    method_setting,
    require,
)
from slamkit.types import Frame, KeyframeKind, TrackingResult


@dataclass
class EveryNKeyframeConfig(PluginConfig):
    """Keyframes at fixed intervals."""

    #: frames between tracking keyframes
    tracking_every: int = method_setting(30)
    #: frames between a keyframe and the next mapping-only keyframe (0: none)
    mapping_every: int = method_setting(0)

    def validate(self) -> None:
        require(self.tracking_every >= 1, "keyframe.tracking_every", "an integer >= 1", self.tracking_every)
        require(self.mapping_every >= 0, "keyframe.mapping_every", "an integer >= 0", self.mapping_every)


class EveryNKeyframePolicy(KeyframePolicy):
    """Keyframes at fixed frame intervals, counted in `frame.index` (so a lost frame, for
    which the pipeline does not ask, does not shift the schedule)."""

    def __init__(self, cfg: EveryNKeyframeConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        self.history = KeyframeHistory()

    def decide(self, frame: Frame, result: TrackingResult) -> KeyframeDecision:
        i = frame.index
        kind = KeyframeKind.NONE
        if self.history.last_tracking is None or i - self.history.last_tracking >= self.cfg.tracking_every:
            kind = KeyframeKind.TRACKING
        elif self.cfg.mapping_every and i - self.history.last_keyframe >= self.cfg.mapping_every:
            kind = KeyframeKind.MAPPING_ONLY
        return KeyframeDecision(self.history.record(i, kind), result.correspondence_ratio)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("every_n", EveryNKeyframePolicy, EveryNKeyframeConfig)]
