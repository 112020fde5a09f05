"""`dataset=rosbag`: RGB-D input from a ROS bag, read with rosbags (pure Python, no ROS needed).

    slamkit dataset=rosbag dataset.path=recording.bag                  # ROS1
    slamkit dataset=rosbag dataset.path=recording/                     # ROS2 bag folder (metadata.yaml)
    slamkit dataset=rosbag dataset.path=recording.mcap dataset.groundtruth=groundtruth.txt

Needs the optional extra `rosbag` (`pip install -e '.[rosbag]'`). The colour and depth topics
are found by their images' encodings when the bag has one of each (else name them with
`dataset.color_topic` / `dataset.depth_topic`); intrinsics come from the CameraInfo topic
(`dataset.camera_info_topic`, or `dataset.fx/fy/cx/cy`); colour and depth are paired by header
stamp within `dataset.sync_tolerance` seconds. Depth is assumed registered to the colour
camera. Encodings and compressed formats: `slamkit_plugins.datasets.rosbag.images`.

Modules: `bag` (opening a bag and reading a topic's k-th message), `images` (sensor_msgs to
arrays), `dataset` (the plugin: config and dataset).
"""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.datasets.rosbag.dataset import RosbagConfig, RosbagDataset

__all__ = ["RosbagConfig", "RosbagDataset"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("rosbag", RosbagDataset, RosbagConfig)]
