"""`loop_closure=pose_graph`: loop detection by place and appearance, geometric verification
(FPFH + RANSAC, then G-ICP), and pose-graph optimisation (gtsam or open3d) of the keyframes.

Modules: `config` (options), `closure` (the plugin: the graph and the steps), `odometry` (the
odometry edges, measured with colour), `detection` (candidates), `verification` (registration
and its acceptance), `optimisation` (the backends).
Needs open3d and, for the default backend, gtsam (the optional extra `loop`).
"""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.loop_closures.pose_graph.closure import PoseGraphLoopClosure
from slamkit_plugins.loop_closures.pose_graph.config import Backend, PoseGraphConfig, WeakDirection

__all__ = ["Backend", "PoseGraphConfig", "PoseGraphLoopClosure", "WeakDirection"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("pose_graph", PoseGraphLoopClosure, PoseGraphConfig)]
