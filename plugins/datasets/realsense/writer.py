"""A RealSense recording written from any dataset's frames, with no camera: `pyrealsense2`'s
`software_device` with a depth and a colour sensor (the dataset's camera for both, the identity
between them: depth registered to colour), a `recorder` writing the .db3 that SDK 2.59 records,
and one `software_video_frame` per image. Each frame's colour and depth are written at the
frame's timestamp (as a D400's synchronised pair: the SDK's syncer pairs a colour and a depth
frame by time), each given at its timestamp's time after the first, so that the recording
plays at the dataset's pace. `dataset=realsense dataset.path=FILE` plays it back; the tests and
benchmarks/realsense_library.py make theirs from the TUM frames."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit_plugins.datasets.realsense.sdk import sdk


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


def raw_depth(frame, k: int, units_per_metre: float) -> np.ndarray:
    """Frame `k`'s depth (metres) as the device's z16: HxW uint16 raw units, `units_per_metre`
    of them a metre, rounded; DataError for a depth beyond z16's range."""
    raw = np.round(np.asarray(frame.depth, dtype=np.float64) * units_per_metre)
    if raw.max(initial=0) > np.iinfo(np.uint16).max:
        raise DataError(f"frame {k}: depth {frame.depth.max():.2f} m beyond z16 at {units_per_metre:g} "
                        "units per metre (expected a smaller units_per_metre)")
    return raw.astype(np.uint16)


def write_recording(dataset, path: Path, units_per_metre: float = 1000.0, fps: int = 30) -> Path:
    """Write every frame of `dataset` (a slamkit Dataset) as a RealSense .db3 recording at
    `path`: colour rgb8, depth z16 of `units_per_metre` raw units per metre (the device's depth
    scale is its inverse; 5000 keeps TUM's 16-bit depth exactly), device timestamps = the
    frames' (seconds, written in milliseconds). DataError for a depth beyond z16's range."""
    rs = sdk()
    if Path(path).suffix != ".db3":
        raise DataError(f"{path}: the RealSense SDK records .db3 files (expected a name ending in .db3)")
    camera = dataset.camera
    device = rs.software_device()
    depth_sensor, color_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    depth = _profile(rs, depth_sensor, rs.stream.depth, rs.format.z16, 2, 0, camera, fps)
    color = _profile(rs, color_sensor, rs.stream.color, rs.format.rgb8, 3, 1, camera, fps)
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    depth.register_extrinsics_to(color, identity)
    depth_sensor.add_read_only_option(rs.option.depth_units, 1.0 / units_per_metre)
    device.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(path), device)
    depth_sensor.open(depth)
    color_sensor.open(color)
    sink = rs.frame_queue(4 * len(dataset) + 8)
    depth_sensor.start(sink)
    color_sensor.start(sink)
    start, first = time.perf_counter(), None
    try:
        for k in range(len(dataset)):
            frame = dataset[k]
            # The recorder stamps each frame with the time it is given, and playback at the
            # recorded pace follows those stamps, not the device timestamps: give each frame at
            # its own time after the first.
            first = frame.timestamp if first is None else first
            wait = start + (frame.timestamp - first) - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            images = ((depth_sensor, depth, raw_depth(frame, k, units_per_metre), 2),
                      (color_sensor, color, np.asarray(frame.rgb), 3))
            for sensor, profile, pixels, bpp in images:
                video = rs.software_video_frame()
                video.pixels = np.ascontiguousarray(pixels)
                video.stride, video.bpp = camera.width * bpp, bpp
                video.timestamp = frame.timestamp * 1000.0  # milliseconds, as the SDK's
                video.domain = rs.timestamp_domain.system_time
                video.frame_number = k
                video.profile = profile.as_video_stream_profile()
                sensor.on_video_frame(video)
    finally:
        for sensor in (depth_sensor, color_sensor):
            sensor.stop()
            sensor.close()
        del recorder  # the recording is complete once the recorder is gone
    return Path(path)
