"""`viewer=none` (the default): nothing is shown or recorded."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, RunContext, Viewer, ViewerFrame


@dataclass
class NoViewerConfig(PluginConfig):
    """No options."""


class NoViewer(Viewer):
    """Shows nothing."""

    def __init__(self, cfg: NoViewerConfig, context: RunContext = RunContext()):
        self.cfg = cfg

    def show(self, view: ViewerFrame) -> None:
        pass


@hookimpl
def slamkit_plugins():
    return [PluginSpec("none", NoViewer, NoViewerConfig)]
