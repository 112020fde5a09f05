"""`loop_closure=none`: no loop closure; the trajectory is the tracker's."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, RunContext
from slamkit.roles.loop_closure import LoopClosure, LoopDecision, LoopKeyframe


@dataclass
class NoLoopClosureConfig(PluginConfig):
    """No options."""


class NoLoopClosure(LoopClosure):
    """Looks for no loops and moves no keyframe."""

    closes_loops = False

    def __init__(self, cfg: NoLoopClosureConfig, context: RunContext = RunContext()):
        self.cfg = cfg

    def add_keyframe(self, keyframe: LoopKeyframe) -> None:
        pass

    def detect_and_optimise(self) -> LoopDecision:
        return LoopDecision()


@hookimpl
def slamkit_plugins():
    return [PluginSpec("none", NoLoopClosure, NoLoopClosureConfig)]
