"""Intel's RealSense SDK (`pyrealsense2`, the optional extra `realsense`) as the `realsense`
dataset uses it: the cameras connected, a camera or a recording opened as a pipeline of
colour + depth frame sets, and one frame set as arrays (`FrameSet`).

Every failure is a one-line DataError saying what is missing: the library, a camera, the
camera asked for, a stream mode the camera does not have, a recording it cannot play."""

from __future__ import annotations

import datetime
import importlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.types import Camera

#: The pip requirement that installs the library (the `realsense` extra).
REQUIREMENT = "pyrealsense2==2.59.1.11053"
#: The recordings the SDK plays: ROS1 bags (every SDK version) and ROS2 SQLite (SDK 2.59 records these).
RECORDING_SUFFIXES = (".bag", ".db3")
#: Milliseconds between two looks at a recording's playback status while waiting for its next frame set.
POLL_MS = 100
#: Milliseconds a recording read to its end is still waited on for its last frame sets.
END_DRAIN_MS = 1000


def sdk():
    """The `pyrealsense2` module; DataError (one line: what to install) where it is not installed
    or does not load."""
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as exc:
        raise DataError(f"dataset=realsense needs Intel's RealSense library, which is not installed ({exc}; "
                        f"expected `pip install \"slamkit[realsense]\"`, i.e. {REQUIREMENT})") from None


@dataclass(frozen=True)
class DeviceInfo:
    """One connected RealSense camera: its model name, serial number, firmware and USB type."""

    name: str
    serial: str
    firmware: str
    usb: str

    def __str__(self) -> str:
        return f"{self.name} serial {self.serial} (firmware {self.firmware}, USB {self.usb})"


def list_devices() -> list[DeviceInfo]:
    """The RealSense cameras connected now (DataError where the library is missing)."""
    rs = sdk()
    devices = []
    for dev in rs.context().query_devices():
        def info(key, dev=dev) -> str:
            return dev.get_info(key) if dev.supports(key) else "?"
        devices.append(DeviceInfo(info(rs.camera_info.name), info(rs.camera_info.serial_number),
                                  info(rs.camera_info.firmware_version), info(rs.camera_info.usb_type_descriptor)))
    return devices


def choose_device(serial: str | None) -> DeviceInfo:
    """The camera to open: the one with serial number `serial`, or the only one connected.
    DataError naming what is connected when there is none, not that one, or several."""
    devices = list_devices()
    if not devices:
        raise DataError("no RealSense camera connected (expected a D400-series camera on USB, seen by the "
                        "RealSense library; dataset.path=FILE plays a .bag or .db3 recording instead)")
    connected = "; ".join(str(d) for d in devices)
    if serial is not None:
        for d in devices:
            if d.serial == serial:
                return d
        raise DataError(f"dataset.serial: no RealSense camera with serial number {serial} is connected "
                        f"(connected: {connected})")
    if len(devices) > 1:
        raise DataError(f"{len(devices)} RealSense cameras connected ({connected}) (expected one; set "
                        "dataset.serial to the serial number of the one to use)")
    return devices[0]


@dataclass
class FrameSet:
    """One colour frame and its depth frame. rgb: HxWx3 uint8; depth_raw: HxW uint16 in the
    device's units (`Stream.depth_scale` metres each), in the colour camera's pixels when
    aligned; timestamp: seconds, the colour frame's device timestamp; number: the colour
    frame's counter (a gap is a frame the camera or the library dropped)."""

    rgb: np.ndarray
    depth_raw: np.ndarray
    timestamp: float
    number: int


class Stream:
    """An open RealSense pipeline of colour + depth frame sets, from a camera (`serial`) or a
    recording (`path`: played one frame set at a time, never dropping one; `real_time`: at its
    recorded pace, as a camera gives them). `camera`: the colour
    camera's intrinsics (pixels); `depth_scale`: metres per raw depth unit; `aligned`: whether
    depth is reprojected into the colour camera by the SDK (`rs.align`); `fps`: the colour
    stream's rate. `where` names the source in errors."""

    def __init__(self, path: Path | None = None, serial: str | None = None, width: int = 640, height: int = 480,
                 fps: int = 30, align: bool = True, real_time: bool = False):
        rs = self.rs = sdk()
        config = rs.config()
        self.path = path
        if path is not None:
            self.where = f"RealSense recording {path}"
            try:
                config.enable_device_from_file(str(path), repeat_playback=False)
            except RuntimeError as exc:
                raise DataError(f"cannot play {self.where}: {_first_line(exc)}") from None
        else:
            device = choose_device(serial)
            self.where = f"RealSense {device}"
            config.enable_device(device.serial)
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        self.pipeline = rs.pipeline()
        try:
            profile = self.pipeline.start(config)
        except RuntimeError as exc:
            wanted = (" (expected a .bag or .db3 recording the RealSense SDK wrote)" if path is not None else
                      f" (expected a {width}x{height} colour and depth mode at {fps} frames/s; set dataset.width, "
                      "dataset.height, dataset.fps)")
            raise DataError(f"cannot start {self.where}: {_first_line(exc)}{wanted}") from None
        self.running = True
        self.last_timestamp_ms: float | None = None  # a recording's last colour timestamp given
        device = profile.get_device()
        self.playback = device.as_playback() if path is not None else None
        if self.playback is not None:
            # real_time: at the recorded pace, frame sets not taken in time dropped (as a camera);
            # else every frame set, at the pace they are taken
            self.playback.set_real_time(real_time)
            # the pipeline started playing before this: from the start again (`next` skips a frame
            # set given twice), so that none is played unseen
            self.playback.pause()
            self.playback.seek(datetime.timedelta(0))
            if not real_time:  # at its recorded pace: paused until the reader is ready (`resume`)
                self.playback.resume()
        try:
            color = profile.get_stream(rs.stream.color).as_video_stream_profile()
            depth = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        except RuntimeError:
            self.stop()
            kinds = ", ".join(str(s.stream_type()).split(".")[-1] for s in profile.get_streams()) or "none"
            raise DataError(f"{self.where} has no colour and depth stream pair (it has: {kinds}; expected both)") \
                from None
        sensor = device.first_depth_sensor()
        self.depth_scale = decimal(sensor.get_depth_scale())
        self.fps = int(color.fps())
        self.camera = _camera(color.get_intrinsics())
        self.color_format = color.format()
        if self.color_format not in (rs.format.rgb8, rs.format.bgr8, rs.format.rgba8, rs.format.bgra8):
            self.stop()
            raise DataError(f"{self.where}: colour stream format {self.color_format} (expected rgb8, bgr8, rgba8 "
                            "or bgra8)")
        registered = _same_camera(depth, color)
        self.aligned = align and not registered
        self.align = rs.align(rs.stream.color) if self.aligned else None
        if not self.aligned and not registered:
            d = depth.get_intrinsics()
            if (d.width, d.height) != (self.camera.width, self.camera.height):
                self.stop()
                raise DataError(f"{self.where}: depth {d.width}x{d.height} and colour {self.camera.width}x"
                                f"{self.camera.height} with dataset.align=false (expected depth aligned to colour)")

    def next(self, timeout_s: float) -> FrameSet | None:
        """The next frame set: None at the end of a recording; DataError when a camera gives
        none within `timeout_s` seconds."""
        deadline = time.monotonic() + timeout_s
        while True:
            ok, frames = self.pipeline.try_wait_for_frames(POLL_MS if self.playback is not None else
                                                           int(timeout_s * 1000))
            if ok or self.playback is None or time.monotonic() > deadline:
                break
            if self.playback.current_status() == self.rs.playback_status.stopped:
                # the file is read to its end; the last frame sets may still be on their way
                ok, frames = self.pipeline.try_wait_for_frames(END_DRAIN_MS)
                if not ok:
                    return None  # the recording's end
                break
        if not ok:
            why = "did it end early?" if self.playback is not None else "is it still connected?"
            raise DataError(f"{self.where} gave no frame in {timeout_s:g} s (expected one every 1/{self.fps} s; "
                            f"{why} dataset.timeout_s waits longer)")
        if self.align is not None:
            frames = self.align.process(frames)
        color, depth = frames.get_color_frame(), frames.get_depth_frame()
        if not color or not depth:
            return self.next(timeout_s)  # a set without its pair (the start of a recording): the next one
        if self.playback is not None:  # one played before the seek to the start, and again after it
            if self.last_timestamp_ms is not None and color.get_timestamp() <= self.last_timestamp_ms:
                return self.next(timeout_s)
            self.last_timestamp_ms = color.get_timestamp()
        rgb = np.asanyarray(color.get_data())
        fmt = self.color_format
        if fmt in (self.rs.format.bgr8, self.rs.format.bgra8):
            rgb = rgb[..., 2::-1]
        rgb = np.ascontiguousarray(rgb[..., :3])
        depth_raw = np.array(np.asanyarray(depth.get_data()), dtype=np.uint16)
        return FrameSet(rgb, depth_raw, color.get_timestamp() / 1000.0, int(color.get_frame_number()))

    def resume(self) -> None:
        """A recording at its recorded pace: start playing (it waits paused from the start)."""
        if self.playback is not None:
            self.playback.resume()

    def stop(self) -> None:
        """Stop the pipeline (the camera's streams, the playback); again is a no-op."""
        if self.running:
            self.running = False
            try:
                self.pipeline.stop()
            except RuntimeError:
                pass


def decimal(value: float) -> float:
    """A float32 the SDK gives (an intrinsic, the depth scale) as the shortest decimal that is that
    float32: 517.3, not 517.2999877929688; 0.001 m, not 0.0010000000474974513."""
    return float(str(np.float32(value)))


def _camera(intrinsics) -> Camera:
    return Camera(int(intrinsics.width), int(intrinsics.height), decimal(intrinsics.fx), decimal(intrinsics.fy),
                  decimal(intrinsics.ppx), decimal(intrinsics.ppy))


def _same_camera(depth, color) -> bool:
    """Whether the depth stream already is in the colour camera: the same intrinsics and an
    identity transform between them (a registered recording), where aligning only resamples."""
    d, c = depth.get_intrinsics(), color.get_intrinsics()
    same = ((d.width, d.height) == (c.width, c.height)
            and np.allclose([d.fx, d.fy, d.ppx, d.ppy], [c.fx, c.fy, c.ppx, c.ppy], atol=1e-6))
    if not same:
        return False
    try:
        extrinsics = depth.get_extrinsics_to(color)
    except RuntimeError:
        return False
    return (np.allclose(np.asarray(extrinsics.rotation), np.eye(3).ravel(), atol=1e-9)
            and np.allclose(extrinsics.translation, 0.0, atol=1e-9))


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
