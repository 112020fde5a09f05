"""The tracking roles: the tracker (a pose per frame) and the keyframe policy."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from slamkit.config import PluginConfig, RunContext
from slamkit.map.gaussian_map import GaussianMap
from slamkit.types import Frame, KeyframeKind, TrackingResult


class Tracker(ABC):
    """Estimates each frame's camera-to-world pose. Built as `cls(config, context)`, complete;
    the map reaches it only through `update_target`."""

    def __init__(self, cfg: PluginConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg

    @abstractmethod
    def track(self, frame: Frame) -> TrackingResult:
        """Pose of `frame` (camera-to-world) against the target of the last `update_target`.
        Must not raise on a bad frame: return `lost=True` with the predicted pose instead."""

    def update_target(self, gaussian_map: GaussianMap) -> None:
        """Called after a tracking keyframe added its Gaussians: rebuild what is aligned to
        from the map (under the map's lock: take a copy, `GaussianMap.tracking_target`)."""

    def initialize(self, first_pose: np.ndarray) -> None:
        """Called once before the first frame with the pose the trajectory starts from."""

    def move_world(self, motion: np.ndarray) -> None:
        """A loop closure moved the world under the tracker: what it tracks against now lies
        at `motion` (4x4 world-frame rigid motion, a point p is now at motion @ p). Move every
        pose it keeps (its motion model) the same way; its target is rebuilt next
        (`update_target`). Called between two frames. A tracker that keeps a map of its own
        moves that too. The default raises NotImplementedError: such a tracker cannot run with
        a loop closure (the run says so before it starts)."""
        raise NotImplementedError(f"{type(self).__name__} does not follow a loop closure's corrections "
                                  "(Tracker.move_world)")

    def state_dict(self) -> dict[str, Any]:
        """What this tracker needs to go on where a run stopped (saved in the map checkpoint,
        `slamkit.run.checkpoint`): JSON values and arrays (numpy or torch). {} by default."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()` (arrays as numpy arrays or CPU tensors), after `initialize`
        and before the next frame. Nothing by default."""


@dataclass
class KeyframeHistory:
    """Frame indices (`frame.index`) of the last tracking keyframe and of the last keyframe of
    any kind; None before the first. Policies count their intervals from these."""

    last_tracking: int | None = None
    last_keyframe: int | None = None

    def record(self, index: int, kind: KeyframeKind) -> KeyframeKind:
        """Note frame `index`'s decision and return it."""
        if kind is KeyframeKind.TRACKING:
            self.last_tracking = index
        if kind:
            self.last_keyframe = index
        return kind


@dataclass(frozen=True)
class KeyframeDecision:
    """What a keyframe policy decided for a frame: its kind, and the correspondence ratio the
    decision was made on (the fraction of trackable frame points close to the map; None for a
    policy that does not measure it)."""

    kind: KeyframeKind
    correspondence_ratio: float | None = None


class KeyframePolicy(ABC):
    """Decides which frames become keyframes, and of which kind. Built as
    `cls(config, context)`."""

    def __init__(self, cfg: PluginConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg

    @abstractmethod
    def decide(self, frame: Frame, result: TrackingResult) -> KeyframeDecision:
        """The keyframe kind of `frame` given its tracking result (which it does not change)."""

    def state_dict(self) -> dict[str, Any]:
        """What the policy needs to go on where a run stopped (the map checkpoint): by default
        its `history` (a KeyframeHistory), if it keeps one there."""
        history = getattr(self, "history", None)
        return {"history": vars(history).copy()} if isinstance(history, KeyframeHistory) else {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()`."""
        if "history" in state and isinstance(getattr(self, "history", None), KeyframeHistory):
            self.history = KeyframeHistory(**state["history"])
