"""A RealSense ROS1 `.bag` recording written from any dataset's frames, with no camera and no SDK:
the layout the RealSense SDK's recorder wrote before SDK 2.59 (librealsense src/media/ros,
`ros_file_format.h`, file version 4), written with `rosbags` (the optional extra `rosbag`).
SDK 2.59 records only `.db3` but still plays these, so the tests and
benchmarks/realsense_library.py make theirs here to play `.bag` recordings.

Layout (device 0; sensor 0 the depth sensor, sensor 1 the colour sensor):

- at the static time (1 ns, the SDK's `TIME_MIN`): `/file_version` (std_msgs/UInt32), the device's
  and each sensor's `info` (diagnostic_msgs/KeyValue: camera info name -> value), each stream's
  `info` (realsense_msgs/StreamInfo: fps, encoding) and `info/camera_info` (sensor_msgs/CameraInfo:
  its intrinsics, pixels), its extrinsics to group 0 `tf/0` (geometry_msgs/Transform: identity,
  depth registered to colour), the depth sensor's `option/Depth Units/value` (std_msgs/Float32:
  metres per raw unit) and `description` (std_msgs/String);
- per frame, at its time after the first (FIRST_FRAME_NS for the first: the recording's pace):
  each stream's `image/data` (sensor_msgs/Image: mono16 depth in raw units, rgb8 colour; header
  stamp = the frame's timestamp, seq = its index) and `image/metadata` (diagnostic_msgs/KeyValue:
  the timestamp domain, system time)."""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit_plugins.datasets.realsense.writer import raw_depth

#: realsense_msgs/StreamInfo, as librealsense's realsense-file defines it (its md5 311d7e24...).
STREAM_INFO_MSG = "uint32 fps\nstring encoding\nbool is_recommended\n"
#: Nanoseconds: the bag time of the static description (the SDK reads it at ROS's TIME_MIN, 1 ns).
STATIC_NS = 1
#: Nanoseconds: the bag time of the first frame, after the static description (the SDK plays
#: frames from 2 ns on), as a recorder's first frame comes after its start.
FIRST_FRAME_NS = 1_000_000
#: The SDK's newest ROS1 file version (with its recommended processing blocks, here none).
FILE_VERSION = 4
#: (sensor index, sensor name, stream name, ROS encoding, bytes per pixel) of the two streams.
STREAMS = ((0, "Stereo Module", "Depth", "mono16", 2), (1, "RGB Camera", "Color", "rgb8", 3))


def _typestore():
    try:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as exc:
        raise DataError(f"writing a RealSense .bag needs rosbags, which is not installed ({exc}; expected "
                        "`pip install \"slamkit[rosbag]\"`)") from None
    typestore = get_typestore(Stores.ROS1_NOETIC)
    typestore.register(get_types_from_msg(STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
    return typestore


def _time(typestore, seconds: float):
    """A ROS time of `seconds` (sec, nsec: exact to the nanosecond for a TUM timestamp)."""
    ns = int(round(seconds * 1e9))
    return typestore.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _static_messages(typestore, camera, units_per_metre: float, fps: int):
    """(topic, type, message) of the device's description: version, infos, streams, depth units."""
    t = typestore.types
    key_value, header = t["diagnostic_msgs/msg/KeyValue"], t["std_msgs/msg/Header"]
    messages = [("/file_version", "std_msgs/msg/UInt32", t["std_msgs/msg/UInt32"](data=FILE_VERSION))]
    messages += [("/device_0/info", "diagnostic_msgs/msg/KeyValue", key_value(key=k, value=v))
                 for k, v in (("Name", "slamkit recording"), ("Serial Number", "0"))]
    k = np.array([camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0])
    p = np.c_[k.reshape(3, 3), np.zeros(3)].ravel()
    roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    identity = t["geometry_msgs/msg/Transform"](
        translation=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    for sensor, name, stream, encoding, _ in STREAMS:
        prefix = f"/device_0/sensor_{sensor}"
        messages.append((f"{prefix}/info", "diagnostic_msgs/msg/KeyValue", key_value(key="Name", value=name)))
        info = t["realsense_msgs/msg/StreamInfo"](fps=fps, encoding=encoding, is_recommended=True)
        camera_info = t["sensor_msgs/msg/CameraInfo"](
            header=header(seq=0, stamp=_time(typestore, 0.0), frame_id=""), height=camera.height,
            width=camera.width, distortion_model="Brown Conrady", D=np.zeros(5), K=k, R=np.eye(3).ravel(), P=p,
            binning_x=0, binning_y=0, roi=roi)
        messages += [(f"{prefix}/{stream}_0/info", "realsense_msgs/msg/StreamInfo", info),
                     (f"{prefix}/{stream}_0/info/camera_info", "sensor_msgs/msg/CameraInfo", camera_info),
                     (f"{prefix}/{stream}_0/tf/0", "geometry_msgs/msg/Transform", identity)]
    option = "/device_0/sensor_0/option/Depth Units"
    messages += [(f"{option}/value", "std_msgs/msg/Float32", t["std_msgs/msg/Float32"](data=1.0 / units_per_metre)),
                 (f"{option}/description", "std_msgs/msg/String",
                  t["std_msgs/msg/String"](data="Number of meters represented by a single depth unit"))]
    return messages


def write_bag_recording(dataset, path: Path, units_per_metre: float = 1000.0, fps: int = 30,
                        color_frames: Collection[int] | None = None) -> Path:
    """Write every frame of `dataset` (a slamkit Dataset) as a RealSense ROS1 .bag at `path`
    (see the module docstring): colour rgb8, depth z16 (mono16) of `units_per_metre` raw units per
    metre (the device's depth scale is its inverse), device timestamps = the frames' (seconds),
    played at the frames' pace; `color_frames`: the frames whose colour is written (None: all; a
    colour stream that starts late or drops frames, as a camera's can). DataError for another
    suffix, an existing file, or a depth beyond z16's range."""
    path = Path(path)
    if path.suffix != ".bag":
        raise DataError(f"{path}: a RealSense ROS1 recording is a .bag file (expected a name ending in .bag)")
    typestore = _typestore()
    from rosbags.rosbag1 import Writer, WriterError

    t = typestore.types
    image, key_value, header = t["sensor_msgs/msg/Image"], t["diagnostic_msgs/msg/KeyValue"], t["std_msgs/msg/Header"]
    camera = dataset.camera
    try:
        writer = Writer(path)
        writer.open()
    except (WriterError, OSError) as exc:  # the file exists, or its folder does not
        raise DataError(f"{path}: cannot write a RealSense .bag here ({exc}; expected a new file in an existing "
                        "folder)") from None
    connections: dict[str, object] = {}

    def write(topic: str, msgtype: str, message, ns: int) -> None:
        if topic not in connections:
            connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
        writer.write(connections[topic], ns, typestore.serialize_ros1(message, msgtype))

    try:
        for topic, msgtype, message in _static_messages(typestore, camera, units_per_metre, fps):
            write(topic, msgtype, message, STATIC_NS)
        first = None
        for k in range(len(dataset)):
            frame = dataset[k]
            first = frame.timestamp if first is None else first
            ns = FIRST_FRAME_NS + int(round((frame.timestamp - first) * 1e9))
            pixels = {"Depth": raw_depth(frame, k, units_per_metre), "Color": np.asarray(frame.rgb, dtype=np.uint8)}
            for sensor, _, stream, encoding, bpp in STREAMS:
                if stream == "Color" and color_frames is not None and k not in color_frames:
                    continue
                prefix = f"/device_0/sensor_{sensor}/{stream}_0/image"
                data = np.ascontiguousarray(pixels[stream]).view(np.uint8).reshape(-1)
                stamp = header(seq=k, stamp=_time(typestore, frame.timestamp), frame_id="")
                write(f"{prefix}/data", "sensor_msgs/msg/Image",
                      image(header=stamp, height=camera.height, width=camera.width, encoding=encoding,
                            is_bigendian=0, step=camera.width * bpp, data=data), ns)
                for key, value in (("timestamp_domain", "System Time"),
                                   ("system_time", str(int(round(frame.timestamp * 1000.0))))):
                    write(f"{prefix}/metadata", "diagnostic_msgs/msg/KeyValue", key_value(key=key, value=value), ns)
    finally:
        writer.close()
    return path
