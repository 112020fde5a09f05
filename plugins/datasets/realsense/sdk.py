"""Intel's RealSense SDK (`pyrealsense2`, the optional extra `realsense`) as the `realsense`
dataset uses it: the library, the cameras connected and the one to open, and the library's
failures as one-line DataErrors saying what is missing (the library, its access to USB, a
camera, the camera asked for), and the one-line errors its sources share (`first_line`,
`no_frame`). The sources: `stream` (a camera or a recording as colour + depth frame sets) and
`playback` (a recording played frame by frame)."""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import numpy as np

from slamkit.errors import DataError

#: The pip requirement that installs the library (the `realsense` extra).
REQUIREMENT = "pyrealsense2==2.59.1.11053"
#: The recordings the SDK plays: ROS1 bags (every SDK version) and ROS2 SQLite (SDK 2.59 records these).
RECORDING_SUFFIXES = (".bag", ".db3")


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
        raise DataError(f"cannot list RealSense cameras: {first_line(exc)} (expected the RealSense library's "
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


def decimal(value: float) -> float:
    """A float32 the SDK gives (an intrinsic, the depth scale) as the shortest decimal that is that
    float32: 517.3, not 517.2999877929688; 0.001 m, not 0.0010000000474974513."""
    return float(str(np.float32(value)))


def no_frame(where: str, timeout_s: float, fps: int, recording: bool) -> DataError:
    """The one line for a source (`where`) that gave no frame in `timeout_s` seconds."""
    why = "did it end early?" if recording else "is it still connected?"
    return DataError(f"{where} gave no frame in {timeout_s:g} s (expected one every 1/{fps} s; {why} "
                     "dataset.timeout_s waits longer)")


def first_line(exc: BaseException) -> str:
    """The library's error (a RuntimeError of many lines) as its first line."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
