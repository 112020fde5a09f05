"""`keyframe=overlap`: the paper's keyframe selection (Sec. 3.1 "Keyframe Selection", Sec. 3.3
"Additional Keyframe Selection for Mapping").

Correspondence ratio = (# trackable frame points whose squared distance to the nearest map
Gaussian, found by the tracker's own correspondence search, is below `overlap_threshold`) /
(# trackable points). It is computed from `result.gaussians.sq_dist_to_map` (no extra search)
and returned with the decision. A frame is a tracking keyframe when the ratio is
below `keyframe_threshold` (the first frame always is); otherwise every `mapping_every`-th
frame after the last keyframe is a mapping-only keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


def correspondence_ratio(result: TrackingResult, overlap_threshold: float) -> float | None:
    """Fraction of the trackable frame points with a map Gaussian closer than
    sqrt(overlap_threshold) (squared distances in m^2, from the tracker's search). Falls back
    to the tracker's own `correspondence_ratio` when it returned no Gaussians; None if neither.
    A frame without trackable points has ratio 0."""
    g = result.gaussians
    if g is None or g.sq_dist_to_map is None:
        return result.correspondence_ratio
    trackable = np.asarray(g.trackable, dtype=bool)
    n = int(trackable.sum())
    if n == 0:
        return 0.0
    return float(np.count_nonzero(np.asarray(g.sq_dist_to_map)[trackable] < overlap_threshold) / n)


@dataclass
class OverlapKeyframeConfig(PluginConfig):
    """The paper's keyframe selection."""

    #: m^2; a frame point overlaps the map below this squared distance (null: the dataset's keyframe_overlap)
    overlap_threshold: float | None = None
    #: a tracking keyframe when the overlapping fraction is below this (null: the dataset's keyframe_threshold)
    keyframe_threshold: float | None = None
    #: a mapping-only keyframe every this many frames after the last keyframe (0: none; reference 10)
    mapping_every: int = method_setting(10)
    #: a tracking keyframe when none was chosen for this many frames (the paper's Fig. 5 rule; 0: never)
    max_interval: int = method_setting(0)

    def validate(self) -> None:
        require(self.overlap_threshold is None or self.overlap_threshold > 0,
                "keyframe.overlap_threshold", "null or > 0 m^2", self.overlap_threshold)
        require(self.keyframe_threshold is None or 0 <= self.keyframe_threshold <= 1,
                "keyframe.keyframe_threshold", "null or in [0, 1]", self.keyframe_threshold)
        require(self.mapping_every >= 0, "keyframe.mapping_every", "an integer >= 0", self.mapping_every)
        require(self.max_interval >= 0, "keyframe.max_interval", "an integer >= 0", self.max_interval)

    def resolve(self, context: RunContext) -> OverlapKeyframeConfig:
        tuning = context.tuning
        return self.fill_nulls(overlap_threshold=tuning.keyframe_overlap, keyframe_threshold=tuning.keyframe_threshold)


class OverlapKeyframePolicy(KeyframePolicy):
    """Tracking keyframes where the frame overlaps the map too little; mapping-only keyframes
    at a fixed interval in between. Frame distances use `frame.index`, so lost frames (for
    which the pipeline does not ask) still count."""

    def __init__(self, cfg: OverlapKeyframeConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        require(cfg.overlap_threshold is not None and cfg.keyframe_threshold is not None, "keyframe",
                "overlap_threshold and keyframe_threshold (OverlapKeyframeConfig.resolve fills them)", cfg)
        self.overlap_threshold = float(cfg.overlap_threshold)
        self.keyframe_threshold = float(cfg.keyframe_threshold)
        self.history = KeyframeHistory()

    def decide(self, frame: Frame, result: TrackingResult) -> KeyframeDecision:
        ratio = correspondence_ratio(result, self.overlap_threshold)
        i = frame.index
        kind = KeyframeKind.NONE
        if self.history.last_tracking is None:
            kind = KeyframeKind.TRACKING
        elif ratio is not None and ratio < self.keyframe_threshold:
            kind = KeyframeKind.TRACKING
        elif self.cfg.max_interval and i - self.history.last_tracking >= self.cfg.max_interval:
            kind = KeyframeKind.TRACKING
        elif self.cfg.mapping_every and i - self.history.last_keyframe >= self.cfg.mapping_every:
            kind = KeyframeKind.MAPPING_ONLY
        return KeyframeDecision(self.history.record(i, kind), ratio)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("overlap", OverlapKeyframePolicy, OverlapKeyframeConfig)]
