"""Intel's RealSense SDK (`pyrealsense2`, the optional extra `realsense`) as the `realsense`
dataset uses it: the cameras connected, a camera or a recording opened as a source of
colour + depth frame sets (`Stream`), and one frame set as arrays (`FrameSet`).

Every failure is a one-line DataError saying what is missing: the library, its access to USB,
a camera, the camera asked for, a stream mode the camera does not have, a recording it cannot play."""

from __future__ import annotations

import collections
import datetime
import importlib
import queue
import threading
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
#: Milliseconds a recording played frame by frame is waited on once it has ended (its end is
#: signalled after its last frames are handed over: one more look).
FILE_END_MS = POLL_MS
#: Frames held between a recording's playback and the reader (the playback waits while it is full).
FILE_QUEUE = 8
#: Seconds of one stream's frames held at the most while waiting for the other's of their time.
HELD_S = 2.0


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
    """The RealSense cameras connected now (DataError where the library is missing or cannot
    enumerate USB devices)."""
    rs = sdk()
    devices = []
    try:
        for dev in rs.context().query_devices():
            def info(key, dev=dev) -> str:
                return dev.get_info(key) if dev.supports(key) else "?"
            devices.append(DeviceInfo(info(rs.camera_info.name), info(rs.camera_info.serial_number),
                                      info(rs.camera_info.firmware_version), info(rs.camera_info.usb_type_descriptor)))
    except RuntimeError as exc:  # the library could not query USB (permissions, a device gone mid-query)
        raise DataError(f"cannot list RealSense cameras: {_first_line(exc)} (expected the RealSense library's "
                        "access to USB devices: its udev rules installed, the camera plugged in)") from None
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
    """An open RealSense source of colour + depth frame sets: a camera (`serial`) or a recording
    at its recorded pace (`real_time`: as a camera gives them) through the SDK's pipeline, or a
    recording played one frame set at a time, never dropping one (`path`; `_FileFrames`).
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
                # frame by frame: the recording's own sensors, not a pipeline (see `_FileFrames`)
                self.file = _FileFrames(rs, path, self.where)
                device, (color, depth) = self.file.device, self.file.profiles
            else:
                device, (color, depth) = self._start_pipeline(path, serial, width, height, fps, real_time)
            self._describe(device, color, depth, align)
        except RuntimeError as exc:  # the SDK refused a query of the device or its streams
            self.stop()
            raise DataError(f"{self.where}: {_first_line(exc)} (expected a colour and a depth stream with their "
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
                raise DataError(f"cannot play {self.where} from its start: {_first_line(exc)}") from None
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
            raise _no_frame(self.where, timeout_s, self.fps, self.playback is not None)
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


class _FileFrames:
    """A recording played frame by frame through its own sensors, without a pipeline: made
    non-real-time and paused before any frame is played, every stream's frames queued as played
    (in order within a stream; the playback waits while the queue is full), and a colour frame
    paired here with the depth frame of its time, so that every pass gives every frame set (the
    pipeline starts a recording in real time and must seek back to its start, and now and then
    lost the first frame set doing so: docs/datasets.md). One queue for all the streams,
    not one each: the SDK reads the file on one thread, in time order, so a stream that runs
    ahead (colour starting late, a gap in one stream) must not fill a queue the reader is not
    emptying. `profiles`: the (colour, depth) stream profiles; `device`: the playback device."""

    def __init__(self, rs, path: Path, where: str):
        self.rs, self.where = rs, where
        self.sensors: list = []  # those started: stopped by `stop`
        self.stopping = threading.Event()
        try:
            self.context = rs.context()
            self.device = self.context.load_device(str(path))
            self.playback = self.device.as_playback()
            self.playback.set_real_time(False)
            self._start(rs)
        except RuntimeError as exc:
            self.stop()
            raise DataError(f"cannot play {where}: {_first_line(exc)} (expected a .bag or .db3 recording the "
                            "RealSense SDK wrote)") from None
        except DataError:
            self.stop()
            raise

    def _start(self, rs) -> None:
        wanted = (rs.stream.color, rs.stream.depth)
        sensors = list(self.device.query_sensors())
        chosen: dict = {}  # stream kind -> (its sensor's index, its profile): the first of each kind
        kinds = []
        for i, sensor in enumerate(sensors):
            for profile in sensor.get_stream_profiles():
                kinds.append(str(profile.stream_type()).split(".")[-1])
                if profile.stream_type() in wanted and profile.stream_type() not in chosen:
                    chosen[profile.stream_type()] = (i, profile)
        if len(chosen) < len(wanted):
            raise DataError(f"{self.where} has no colour and depth stream pair (it has: {', '.join(kinds) or 'none'}; "
                            "expected both)")
        self.profiles = tuple(chosen[kind][1].as_video_stream_profile() for kind in wanted)
        rates = [p.fps() for p in self.profiles]
        if min(rates) <= 0:
            raise DataError(f"{self.where}: colour and depth at {rates[0]} and {rates[1]} frames/s (expected both > 0)")
        self.fps = rates[0]
        # colour and depth within half the faster stream's period are one frame set: at most one
        # frame of the faster stream is that near a frame of the other
        self.tolerance_ms = 500.0 / max(rates)
        self.played: queue.Queue = queue.Queue(FILE_QUEUE)  # every stream's frames, in the order played
        # frames taken from `played` and not paired yet, by stream kind: a frame of one stream
        # waits for the other's of its time (held HELD_S at the most: the file is read in time order)
        self.held = {kind: collections.deque(maxlen=max(1, int(HELD_S * rate))) for kind, rate in zip(wanted, rates)}
        # paused while the sensors start one after the other: a frame played before its sensor
        # has started is lost (a .bag's first colour frame, now and then, unpaused)
        self.playback.pause()
        for sensor in [sensors[i] for i in sorted({i for i, _ in chosen.values()})]:
            sensor.open([p for i, p in chosen.values() if sensors[i] is sensor])
            self.sensors.append(sensor)
            sensor.start(self._queued)
        self.playback.resume()  # (its status now reads "playing" until the file's end)
        # a (colour, depth) pair the SDK did not pair itself, as the frame set `rs.align` takes
        self._depth: list = []
        self._composer = rs.processing_block(
            lambda frame, source: source.frame_ready(source.allocate_composite_frame([frame, *self._depth])))
        self._composed = rs.frame_queue(1)
        self._composer.start(self._composed)

    def _queued(self, frame) -> None:
        """The sensors' callback (the SDK's thread of each stream): the frame into `played`, waiting
        while it is full."""
        frame.keep()
        while not self.stopping.is_set():
            try:
                self.played.put(frame, timeout=POLL_MS / 1000)
                return
            except queue.Full:
                pass

    def next(self, timeout_s: float):
        """The next (colour, depth) frames of one time; None at the recording's end. A frame whose
        other half was never recorded (none within `tolerance_ms`) is passed over."""
        colors, depths = self.held[self.rs.stream.color], self.held[self.rs.stream.depth]
        while True:
            while colors and depths:
                tc, td = colors[0].get_timestamp(), depths[0].get_timestamp()
                if abs(tc - td) <= self.tolerance_ms:
                    return colors.popleft(), depths.popleft()
                (colors if tc < td else depths).popleft()
            frame = self._take(timeout_s)
            if frame is None:
                return None
            self.held[frame.get_profile().stream_type()].append(frame)

    def _take(self, timeout_s: float):
        """The next frame played: None once the playback has stopped at the file's end and no
        frame came for FILE_END_MS; DataError when none came within `timeout_s` while it played."""
        deadline, ended = time.monotonic() + timeout_s, None
        while True:
            playback = self.playback
            if self.stopping.is_set() or playback is None:  # stopped by another thread (the run's end)
                raise DataError(f"{self.where} was closed while a frame was being read")
            try:
                return self.played.get(timeout=POLL_MS / 1000)
            except queue.Empty:
                pass
            now = time.monotonic()
            if playback.current_status() == self.rs.playback_status.stopped:
                ended = ended or now + FILE_END_MS / 1000  # the last frames may still be on their way
                if now > ended:
                    return None
            elif now > deadline:
                raise _no_frame(self.where, timeout_s, self.fps, True)

    def frame_set(self, color, depth):
        """`color` and `depth` as one frame set (what `rs.align` takes)."""
        composer, composed = self._composer, self._composed
        if composer is None or composed is None:
            raise DataError(f"{self.where} was closed while a frame was being read")
        self._depth[:] = [depth]
        composer.invoke(color)
        return composed.wait_for_frame().as_frameset()

    def stop(self) -> None:
        """Stop the sensors and let the playback go now: a playback device stopped mid-file and
        destroyed only at the interpreter's exit aborts it ("FATAL: exception not rethrown")."""
        self.stopping.set()  # a callback waiting on a full queue returns
        for sensor in self.sensors:
            for step in (sensor.stop, sensor.close):
                try:
                    step()
                except RuntimeError:
                    pass
        played = getattr(self, "played", None)  # the frames kept for the reader go now (`held`'s: with it)
        while played is not None:
            try:
                played.get_nowait()
            except queue.Empty:  # (a read on another thread may take the last one first)
                break
        getattr(self, "_depth", []).clear()
        self.sensors, self.profiles, self._composer, self._composed = [], (), None, None
        self.device = self.playback = self.context = None


def _no_frame(where: str, timeout_s: float, fps: int, recording: bool) -> DataError:
    why = "did it end early?" if recording else "is it still connected?"
    return DataError(f"{where} gave no frame in {timeout_s:g} s (expected one every 1/{fps} s; {why} "
                     "dataset.timeout_s waits longer)")


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
