"""Writing small ROS bags from the real TUM frames with rosbags, for the rosbag dataset's tests.

`write_tum_bag(tum_folder, out, n, storage=...)` writes the first `n` colour and depth images of
a TUM RGB-D folder (rgb.txt / depth.txt order, their own timestamps as header stamps and record
times) and a CameraInfo with TUM fr1's intrinsics, in the chosen encodings.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
from PIL import Image

from slamkit.formats.tum import read_tum_list

#: TUM fr1 (slamkit_plugins.datasets.tum.CAMERAS["fr1"]), as a CameraInfo would carry it
FR1_K = (517.3, 0.0, 318.6, 0.0, 516.5, 255.3, 0.0, 0.0, 1.0)
TUM_DEPTH_SCALE = 5000.0


def tum_images(tum: Path, n: int):
    """[(stamp, path)] of the first n colour and depth images."""
    out = []
    for name in ("rgb.txt", "depth.txt"):
        ts, files = read_tum_list(tum / name)
        out.append([(float(t), tum / f) for t, f in zip(ts[:n], files[:n])])
    return out


def _stamp(typestore, t: float):
    Time = typestore.types["builtin_interfaces/msg/Time"]
    sec = int(np.floor(t))
    return Time(sec=sec, nanosec=int(round((t - sec) * 1e9)))


def _header(typestore, t: float, frame_id: str, ros1: bool):
    Header = typestore.types["std_msgs/msg/Header"]
    if ros1:
        return Header(seq=0, stamp=_stamp(typestore, t), frame_id=frame_id)
    return Header(stamp=_stamp(typestore, t), frame_id=frame_id)


def _image(typestore, t, array: np.ndarray, encoding: str, ros1: bool):
    Image_ = typestore.types["sensor_msgs/msg/Image"]
    h, w = array.shape[:2]
    data = np.ascontiguousarray(array).view(np.uint8).reshape(-1)
    return Image_(header=_header(typestore, t, "camera", ros1), height=h, width=w, encoding=encoding,
                  is_bigendian=0, step=data.size // h, data=data)


def _compressed(typestore, t, data: bytes, fmt: str, ros1: bool):
    C = typestore.types["sensor_msgs/msg/CompressedImage"]
    return C(header=_header(typestore, t, "camera", ros1), format=fmt, data=np.frombuffer(data, np.uint8))


def _encode(image: Image.Image, fmt: str) -> bytes:
    buf = io.BytesIO()
    image.save(buf, format=fmt, quality=95) if fmt == "JPEG" else image.save(buf, format=fmt)
    return buf.getvalue()


def _camera_info(typestore, t, w: int, h: int, ros1: bool, k=FR1_K):
    CameraInfo = typestore.types["sensor_msgs/msg/CameraInfo"]
    RegionOfInterest = typestore.types["sensor_msgs/msg/RegionOfInterest"]
    roi = RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    d, k_, r = np.zeros(5), np.array(k, float), np.eye(3).ravel()
    p = np.c_[np.array(k).reshape(3, 3), np.zeros(3)].ravel()
    fields = dict(header=_header(typestore, t, "camera", ros1), height=h, width=w, distortion_model="plumb_bob",
                  binning_x=0, binning_y=0, roi=roi)
    if ros1:
        return CameraInfo(D=d, K=k_, R=r, P=p, **fields)
    return CameraInfo(d=d, k=k_, r=r, p=p, **fields)


def color_message(typestore, t, path: Path, color: str, ros1: bool):
    im = Image.open(path).convert("RGB")
    if color in ("jpeg", "png"):
        return "sensor_msgs/msg/CompressedImage", _compressed(typestore, t, _encode(im, color.upper()), color, ros1)
    rgb = np.asarray(im)
    array = {"rgb8": rgb, "bgr8": rgb[:, :, ::-1], "mono8": rgb[:, :, 1]}[color]
    return "sensor_msgs/msg/Image", _image(typestore, t, array, color, ros1)


def depth_message(typestore, t, path: Path, depth: str, ros1: bool, size=None):
    raw = np.asarray(Image.open(path)).astype(np.uint16)  # TUM: 5000 units per metre
    if size is not None:
        raw = np.asarray(Image.fromarray(raw).resize(size, Image.NEAREST))
    if depth == "16UC1":
        return "sensor_msgs/msg/Image", _image(typestore, t, raw, "16UC1", ros1)
    if depth == "32FC1":
        metres = raw.astype(np.float32) / np.float32(TUM_DEPTH_SCALE)
        return "sensor_msgs/msg/Image", _image(typestore, t, metres, "32FC1", ros1)
    assert depth == "compressedDepth"
    png = _encode(Image.fromarray(raw), "PNG")
    header = struct.pack("<iff", 0, 0.0, 0.0)
    message = _compressed(typestore, t, header + png, "16UC1; compressedDepth png", ros1)
    return "sensor_msgs/msg/CompressedImage", message


def write_tum_bag(tum: Path, out: Path, n: int, storage: str = "ros1", color: str = "rgb8", depth: str = "16UC1",
                  camera_info: bool = True, image_topics: bool = True, depth_size=None) -> Path:
    """Write a bag of the first n TUM frames; storage: ros1 (.bag), sqlite3 or mcap (a ROS2
    bag folder, `out`). Topics: /camera/rgb/image_color, /camera/depth/image,
    /camera/rgb/camera_info. Returns the path to give dataset.path."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = storage == "ros1"
    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    colors, depths = tum_images(tum, n)
    w, h = Image.open(colors[0][1]).size
    messages = []  # (t, topic, msgtype, message)
    if image_topics:
        messages += [(t, "/camera/rgb/image_color", *color_message(typestore, t, p, color, ros1)) for t, p in colors]
        messages += [(t, "/camera/depth/image", *depth_message(typestore, t, p, depth, ros1, depth_size))
                     for t, p in depths]
    if camera_info:
        messages += [(t, "/camera/rgb/camera_info", "sensor_msgs/msg/CameraInfo",
                      _camera_info(typestore, t, w, h, ros1)) for t, _ in colors]
    messages.sort(key=lambda m: (m[0], m[1]))
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(out)
        serialize = typestore.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(out, version=9, storage_plugin=plugin)
        serialize = typestore.serialize_cdr
    with writer:
        conns = {}
        for t, topic, msgtype, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            writer.write(conns[topic], int(round(t * 1e9)), serialize(msg, msgtype))
    return out
