"""An open RealSense source of colour + depth frame sets (`Stream`): a camera, or a recording at
its recorded pace through the SDK's pipeline, or a recording played frame by frame
(`playback.RecordingPlayback`); one frame set as arrays (`FrameSet`). Every failure is a one-line
DataError: a stream mode the camera does not have, a recording it cannot play, no frame in time."""

from __future__ import annotations

import datetime
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.types import Camera
from slamkit_plugins.datasets.realsense.playback import POLL_MS, RecordingPlayback
from slamkit_plugins.datasets.realsense.sdk import choose_device, decimal, first_line, no_frame, sdk

#: Milliseconds a recording read to its end is still waited on for its last frame sets.
END_DRAIN_MS = 1000


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
    """An open RealSense source of colour + depth frame sets: a camera (`serial`) or a recording
    at its recorded pace (`real_time`: as a camera gives them) through the SDK's pipeline, or a
    recording played one frame set at a time, never dropping one (`path`; `RecordingPlayback`).
    `camera`: the colour camera's intrinsics (pixels); `depth_scale`: metres per raw depth unit;
    `aligned`: whether depth is reprojected into the colour camera by the SDK (`rs.align`);
    `fps`: the colour stream's rate. `where` names the source in errors."""

    def __init__(self, path: Path | None = None, serial: str | None = None, width: int = 640, height: int = 480,
                 fps: int = 30, align: bool = True, real_time: bool = False):
        rs = self.rs = sdk()
        self.path = path
        self.running = True
        self.last_timestamp_ms: float | None = None  # a recording's last colour timestamp given
        self.pipeline = self.playback = self.file = None  # what plays: a pipeline, or a file frame by frame
        self.where = f"RealSense recording {path}" if path is not None else "RealSense camera"
        # whatever started stops on any failure here: a playback left running aborts the
        # interpreter at its exit
        try:
            if path is not None and not real_time:
                # frame by frame: the recording's own sensors, not a pipeline (see `RecordingPlayback`)
                self.file = RecordingPlayback(rs, path, self.where)
                device, (color, depth) = self.file.device, self.file.profiles
            else:
                device, (color, depth) = self._start_pipeline(path, serial, width, height, fps, real_time)
            self._describe(device, color, depth, align)
        except RuntimeError as exc:  # the SDK refused a query of the device or its streams
            self.stop()
            raise DataError(f"{self.where}: {first_line(exc)} (expected a colour and a depth stream with their "
                            "intrinsics and a depth scale)") from None
        except DataError:
            self.stop()
            raise

    def _describe(self, device, color, depth, align: bool) -> None:
        """The depth scale, rate, colour camera and format, and whether to align, from the source."""
        rs = self.rs
        self.depth_scale = decimal(device.first_depth_sensor().get_depth_scale())
        self.fps = int(color.fps())
        self.camera = _camera(color.get_intrinsics())
        self.color_format = color.format()
        if self.color_format not in (rs.format.rgb8, rs.format.bgr8, rs.format.rgba8, rs.format.bgra8):
            raise DataError(f"{self.where}: colour stream format {self.color_format} (expected rgb8, bgr8, rgba8 "
                            "or bgra8)")
        registered = _same_camera(depth, color)
        self.aligned = align and not registered
        self.align = rs.align(rs.stream.color) if self.aligned else None
        if not self.aligned and not registered:
            d = depth.get_intrinsics()
            if (d.width, d.height) != (self.camera.width, self.camera.height):
                raise DataError(f"{self.where}: depth {d.width}x{d.height} and colour {self.camera.width}x"
                                f"{self.camera.height} with dataset.align=false (expected depth aligned to colour)")

    def _start_pipeline(self, path, serial, width, height, fps, real_time):
        """A camera, or a recording at its recorded pace, through the SDK's pipeline (its colour and
        depth paired by the SDK as they come): (device, (colour profile, depth profile))."""
        rs = self.rs
        config = rs.config()
        if path is not None:
            try:
                config.enable_device_from_file(str(path), repeat_playback=False)
            except RuntimeError as exc:
                raise DataError(f"cannot play {self.where}: {first_line(exc)}") from None
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
            raise DataError(f"cannot start {self.where}: {first_line(exc)}{wanted}") from None
        device = profile.get_device()
        if path is not None:
            # at its recorded pace, frame sets not taken in time dropped (as a camera); the pipeline
            # started playing before this: paused at the start again (`next` skips a frame set given
            # twice) until the reader is ready (`resume`)
            try:
                self.playback = device.as_playback()
                self.playback.set_real_time(real_time)
                self.playback.pause()
                self.playback.seek(datetime.timedelta(0))
            except RuntimeError as exc:
                raise DataError(f"cannot play {self.where} from its start: {first_line(exc)}") from None
        try:
            return device, (profile.get_stream(rs.stream.color).as_video_stream_profile(),
                            profile.get_stream(rs.stream.depth).as_video_stream_profile())
        except RuntimeError:
            kinds = ", ".join(str(s.stream_type()).split(".")[-1] for s in profile.get_streams()) or "none"
            raise DataError(f"{self.where} has no colour and depth stream pair (it has: {kinds}; expected both)") \
                from None

    def next(self, timeout_s: float) -> FrameSet | None:
        """The next frame set: None at the end of a recording; DataError when none comes within
        `timeout_s` seconds (a camera, or a recording still playing)."""
        if self.file is not None:
            pair = self.file.next(timeout_s)
            if pair is None:
                return None  # the recording's end
            color, depth = pair
            if self.align is not None:
                frames = self.align.process(self.file.frame_set(color, depth))
                color, depth = frames.get_color_frame(), frames.get_depth_frame()
            return self._frame_set(color, depth)
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
            raise no_frame(self.where, timeout_s, self.fps, self.playback is not None)
        if self.align is not None:
            frames = self.align.process(frames)
        color, depth = frames.get_color_frame(), frames.get_depth_frame()
        if not color or not depth:
            return self.next(timeout_s)  # a set without its pair (the start of a recording): the next one
        if self.playback is not None:  # one played before the seek to the start, and again after it
            if self.last_timestamp_ms is not None and color.get_timestamp() <= self.last_timestamp_ms:
                return self.next(timeout_s)
            self.last_timestamp_ms = color.get_timestamp()
        return self._frame_set(color, depth)

    def _frame_set(self, color, depth) -> FrameSet:
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
        """Stop the source (the camera's streams, the playback); again is a no-op."""
        if self.running:
            self.running = False
            if self.file is not None:
                self.file.stop()
            try:
                if self.pipeline is not None:
                    self.pipeline.stop()
            except RuntimeError:
                pass


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
