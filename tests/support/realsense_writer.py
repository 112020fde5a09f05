"""RealSense recordings of the real TUM frames, made with no camera: `pyrealsense2`'s
`software_device` with a depth and a colour sensor (the TUM fr1 camera's intrinsics, the same
for both, the identity between them: depth registered to colour, as TUM's is), a `recorder`
writing the .db3 that SDK 2.59 records, and one `software_video_frame` per image, a colour
image and the depth image TUM associates with it both at the colour's TUM timestamp (as a
D400's synchronised pair: the SDK's syncer pairs a colour and a depth frame by time, and TUM's
are up to 20 ms apart). `dataset=realsense dataset.path=FILE` plays it back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from slamkit.formats.tum import associate, read_tum_list
from slamkit_plugins.datasets.tum import CAMERAS

#: TUM's 16-bit depth: 5000 units per metre, so the device's depth scale is 1 / 5000 metres per unit.
TUM_UNITS_PER_METRE = 5000.0


def _profile(rs, sensor, kind, fmt, bpp: int, uid: int, camera, fps: int):
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height = camera.width, camera.height
    intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy = camera.fx, camera.fy, camera.cx, camera.cy
    intrinsics.model, intrinsics.coeffs = rs.distortion.none, [0.0] * 5
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = kind, 0, uid
    stream.width, stream.height, stream.fps, stream.bpp, stream.fmt = camera.width, camera.height, fps, bpp, fmt
    stream.intrinsics = intrinsics
    return sensor.add_video_stream(stream)


def write_tum_recording(tum: Path, path: Path, n: int, fps: int = 30) -> Path:
    """A RealSense .db3 recording at `path` of the first `n` associated colour + depth frames of
    the TUM folder `tum` (colour rgb8, depth z16 in TUM's units, device timestamps = TUM's colour
    timestamps)."""
    import pyrealsense2 as rs

    rgb_ts, rgb_files = read_tum_list(tum / "rgb.txt")
    depth_ts, depth_files = read_tum_list(tum / "depth.txt")
    ic, idepth = associate(rgb_ts, depth_ts, 0.02)
    camera = CAMERAS["fr1"]
    device = rs.software_device()
    depth_sensor, color_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    depth = _profile(rs, depth_sensor, rs.stream.depth, rs.format.z16, 2, 0, camera, fps)
    color = _profile(rs, color_sensor, rs.stream.color, rs.format.rgb8, 3, 1, camera, fps)
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    depth.register_extrinsics_to(color, identity)
    depth_sensor.add_read_only_option(rs.option.depth_units, 1.0 / TUM_UNITS_PER_METRE)
    device.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(path), device)
    depth_sensor.open(depth)
    color_sensor.open(color)
    sink = rs.frame_queue(4 * n + 8)
    depth_sensor.start(sink)
    color_sensor.start(sink)
    for k, (c, d) in enumerate(zip(ic[:n], idepth[:n])):
        images = (
            (depth_sensor, depth, np.asarray(Image.open(tum / depth_files[d])).astype(np.uint16), 2, rgb_ts[c]),
            (color_sensor, color, np.asarray(Image.open(tum / rgb_files[c]).convert("RGB")), 3, rgb_ts[c]),
        )
        for sensor, profile, pixels, bpp, stamp in images:
            frame = rs.software_video_frame()
            frame.pixels = np.ascontiguousarray(pixels)
            frame.stride, frame.bpp = camera.width * bpp, bpp
            frame.timestamp = float(stamp) * 1000.0  # milliseconds, as the SDK's
            frame.domain = rs.timestamp_domain.system_time
            frame.frame_number = k
            frame.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(frame)
    for sensor in (depth_sensor, color_sensor):
        sensor.stop()
        sensor.close()
    del recorder  # the recording is complete once the recorder is gone
    return path
