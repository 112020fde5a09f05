"""`tracker=gicp`: GS-ICP SLAM's G-ICP tracking against the shared Gaussian map.

Modules: `config` (options), `tracker` (the plugin: per frame and per tracking keyframe),
`target` (the aligned-to map Gaussians), `alignment` (the Levenberg-Marquardt solve),
`fallbacks` (which other starts to try when an alignment is not trusted), `kernels` (the loops
over points, compiled or numpy).
"""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.trackers.gicp.config import GICPConfig, InitialGuess
from slamkit_plugins.trackers.gicp.tracker import GICPTracker

__all__ = ["GICPConfig", "GICPTracker", "InitialGuess"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("gicp", GICPTracker, GICPConfig)]
