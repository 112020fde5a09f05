"""`tracker=gicp`: GS-ICP SLAM's G-ICP tracking against the shared Gaussian map (see `.tracker`)."""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.trackers.gicp.tracker import GICPConfig, GICPTracker, InitialGuess, orthonormalize

__all__ = ["GICPConfig", "GICPTracker", "InitialGuess", "orthonormalize"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("gicp", GICPTracker, GICPConfig)]
