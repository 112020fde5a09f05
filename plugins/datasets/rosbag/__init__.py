"""`dataset=rosbag`: RGB-D input from a ROS1 or ROS2 bag, read with rosbags (pure Python, no ROS
needed; the optional extra `rosbag`).

The colour and depth topics are found by their images' encodings when the bag has one of each
(else `dataset.color_topic` / `dataset.depth_topic`); intrinsics come from a CameraInfo topic or
`dataset.fx/fy/cx/cy`; colour and depth are paired by header stamp within
`dataset.sync_tolerance`; depth must be registered to the colour camera (docs/datasets.md,
"`rosbag`: ROS1 and ROS2 bags"). Modules: `bag` (opening a bag, reading a topic's k-th message),
`images` (sensor_msgs to arrays), `dataset` (the plugin: config and dataset).
"""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.datasets.rosbag.dataset import RosbagConfig, RosbagDataset

__all__ = ["RosbagConfig", "RosbagDataset"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("rosbag", RosbagDataset, RosbagConfig)]
