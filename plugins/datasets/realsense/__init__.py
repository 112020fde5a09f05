"""`dataset=realsense`: an Intel RealSense D400-series camera live, or a RealSense recording
(`dataset.path=FILE`: the SDK's .bag, or the .db3 that SDK 2.59 records), read with Intel's
`pyrealsense2` (the optional extra `realsense`; docs/dependencies.md says why this library).

Live: the device's own colour intrinsics and depth scale, depth aligned to colour by the SDK, the
device's timestamps, the resolution and rate asked for (`dataset.width/height/fps`), the camera
picked by `dataset.serial` among several; the run is real time with realtime.drop_frames unless the
command line says otherwise, and Ctrl-C ends it with its outputs written. `dataset.record=DIR`
keeps the frames in the TUM layout. docs/datasets.md, "`realsense`: a RealSense camera, live or
recorded". Modules: `sdk` (the library and its cameras), `stream` (a camera or recording as frame
sets), `playback` (a recording played frame by frame), `capture` (a live source's capture thread),
`recording` (the TUM layout writer), `dataset` (the plugin: config and dataset); recordings made
with no camera from any dataset's frames: `writer` (a .db3, with the SDK's software device and
recorder) and `bag` (a ROS1 .bag in the SDK's layout, with rosbags).
"""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.datasets.realsense.dataset import RealSenseConfig, RealSenseDataset

__all__ = ["RealSenseConfig", "RealSenseDataset"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("realsense", RealSenseDataset, RealSenseConfig)]
