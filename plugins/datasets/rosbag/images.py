"""sensor_msgs images and camera info, decoded into slamkit's arrays (numpy and Pillow only).

- `sensor_msgs/Image`: colour in rgb8, bgr8, rgba8, bgra8 or mono8 (HxWx3 uint8 RGB out); depth
  in 16UC1 / mono16 (raw units, metres = raw / depth_scale; millimetres: 1000) or 32FC1 (metres).
  Rows may be padded (`step`), big-endian data is honoured.
- `sensor_msgs/CompressedImage`: colour as JPEG or PNG (`format` "jpeg", "png", "bgr8; jpeg
  compressed bgr8", ...); depth as image_transport's compressedDepth ("16UC1; compressedDepth
  png": a 12-byte header, then a 16-bit PNG of raw units; "32FC1; compressedDepth": the PNG holds
  quantised inverse depth, metres = A / (raw - B) with A, B from the header) or as a plain 16-bit
  PNG ("16UC1; png").
- `sensor_msgs/CameraInfo`: K (ROS1 `K`, ROS2 `k`; row-major 3x3, pixels) and the image size.

Depth out: HxW float32 metres, 0 = invalid (0, negative, NaN or infinite raw values).
Every failure raises `slamkit.errors.DataError` with one line naming `where` (bag, topic, stamp).
"""

from __future__ import annotations

import io

import numpy as np
from PIL import Image as PILImage

from slamkit.errors import DataError
from slamkit.types import Camera

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE_TYPES = (IMAGE, COMPRESSED)

#: encoding -> (channels, which channels are R, G, B)
COLOR_ENCODINGS = {"rgb8": (3, (0, 1, 2)), "bgr8": (3, (2, 1, 0)), "rgba8": (4, (0, 1, 2)),
                   "bgra8": (4, (2, 1, 0)), "mono8": (1, (0, 0, 0)), "8uc3": (3, (2, 1, 0)), "8uc1": (1, (0, 0, 0))}
#: encoding -> dtype of the raw depth
DEPTH_ENCODINGS = {"16uc1": np.uint16, "mono16": np.uint16, "32fc1": np.float32}
COLOR_EXPECTED = "rgb8, bgr8, rgba8, bgra8 or mono8, or a JPEG / PNG CompressedImage"
DEPTH_EXPECTED = "16UC1 or mono16 (raw units, depth_scale per metre) or 32FC1 (metres), or compressedDepth"
#: image_transport's compressedDepth header: int32 format, float32 depthQuantA, float32 depthQuantB
COMPRESSED_DEPTH_HEADER = 12


def is_depth(msg, msgtype: str) -> bool:
    """Whether an image message holds depth (by its encoding, or its compressed format)."""
    if msgtype == IMAGE:
        return msg.encoding.lower() in DEPTH_ENCODINGS
    fmt = msg.format.lower()
    return "compresseddepth" in fmt or fmt.split(";")[0].strip() in DEPTH_ENCODINGS


def image_size(msg, msgtype: str, where: str) -> tuple[int, int]:
    """(width, height) in pixels (a compressed image is decoded for it)."""
    if msgtype == IMAGE:
        return int(msg.width), int(msg.height)
    if is_depth(msg, msgtype):
        return _compressed_depth_png(msg, where).size
    return _open(bytes(msg.data), where, "a JPEG or PNG image").size


def decode_color(msg, msgtype: str, where: str) -> np.ndarray:
    """HxWx3 uint8 RGB from an Image or CompressedImage message."""
    if msgtype == COMPRESSED:
        im = _open(bytes(msg.data), where, "a JPEG or PNG colour image")
        if im.mode in ("I;16", "I;16B", "I", "F"):
            raise DataError(f"{where}: a {im.mode} image (expected colour: {COLOR_EXPECTED})")
        return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    encoding = msg.encoding.lower()
    if encoding not in COLOR_ENCODINGS:
        raise DataError(f"{where}: encoding {msg.encoding!r} (expected colour: {COLOR_EXPECTED})")
    channels, rgb = COLOR_ENCODINGS[encoding]
    pixels = _pixels(msg, np.uint8, channels, where)
    return np.ascontiguousarray(pixels[:, :, list(rgb)])


def decode_depth(msg, msgtype: str, depth_scale: float, where: str) -> np.ndarray:
    """HxW float32 metres (0 = invalid) from an Image or CompressedImage message; 16-bit raw
    depth is divided by `depth_scale` (raw units per metre)."""
    if msgtype == COMPRESSED:
        raw = _decode_compressed_depth(msg, where)
        if raw.dtype == np.float32:
            return _valid_metres(raw)
    else:
        encoding = msg.encoding.lower()
        if encoding not in DEPTH_ENCODINGS:
            raise DataError(f"{where}: encoding {msg.encoding!r} (expected depth: {DEPTH_EXPECTED})")
        raw = _pixels(msg, DEPTH_ENCODINGS[encoding], 1, where)[:, :, 0]
        if raw.dtype == np.float32:
            return _valid_metres(raw.astype(np.float32))
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[raw == 0] = 0.0
    return depth


def camera_from_info(msg, where: str) -> Camera:
    """Pinhole intrinsics (pixels) and image size of a CameraInfo message."""
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64).ravel()
    if k.size != 9 or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise DataError(f"{where}: K = {k.tolist()} for {msg.width}x{msg.height} "
                        "(expected a calibrated camera: fx, fy > 0 and the image size)")
    return Camera(int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]))


def distortion(msg) -> np.ndarray:
    """The CameraInfo's distortion coefficients (ROS1 `D`, ROS2 `d`)."""
    return np.asarray(msg.d if hasattr(msg, "d") else msg.D, dtype=np.float64)


# -- helpers ------------------------------------------------------------------------------------
def _pixels(msg, dtype, channels: int, where: str) -> np.ndarray:
    """HxWxC array of an Image message's data, honouring its row step and byte order."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row = w * channels * dt.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < row or data.size < step * (h - 1) + row:
        raise DataError(f"{where}: {data.size} bytes for a {w}x{h} {msg.encoding} image with row step {step} "
                        f"(expected at least {step * (h - 1) + row})")
    if data.size < step * h:  # a last row without its padding
        data = np.concatenate([data, np.zeros(step * h - data.size, np.uint8)])
    rows = data[: step * h].reshape(h, step)[:, :row]
    return np.ascontiguousarray(rows).view(dt).reshape(h, w, channels).astype(dt.newbyteorder("="))


def _open(data: bytes, where: str, expected: str) -> PILImage.Image:
    try:
        im = PILImage.open(io.BytesIO(data))
        im.load()
        return im
    except (OSError, ValueError, SyntaxError, PILImage.DecompressionBombError) as exc:
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise DataError(f"{where}: cannot decode the compressed image: {reason} (expected {expected})") from None


def _compressed_depth_png(msg, where: str) -> PILImage.Image:
    data = bytes(msg.data)
    if "compresseddepth" in msg.format.lower():
        data = data[COMPRESSED_DEPTH_HEADER:]
    return _open(data, where, "a 16-bit PNG after the compressedDepth header")


def _decode_compressed_depth(msg, where: str) -> np.ndarray:
    """uint16 raw units, or float32 metres for 32FC1 compressedDepth."""
    im = _compressed_depth_png(msg, where)
    if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise DataError(f"{where}: compressed depth of pixel mode {im.mode} (expected a 16-bit PNG)")
    raw = np.asarray(im).astype(np.uint16)
    if msg.format.lower().startswith("32fc1"):
        header = np.frombuffer(bytes(msg.data)[:COMPRESSED_DEPTH_HEADER], dtype="<f4", offset=4, count=2)
        quant_a, quant_b = float(header[0]), float(header[1])
        with np.errstate(divide="ignore", invalid="ignore"):
            metres = np.float32(quant_a) / (raw.astype(np.float32) - np.float32(quant_b))
        metres[raw == 0] = 0.0
        return _valid_metres(metres)
    return raw


def _valid_metres(depth: np.ndarray) -> np.ndarray:
    depth = np.array(depth, dtype=np.float32)
    depth[~np.isfinite(depth) | (depth <= 0)] = 0.0
    return depth
