"""Reading colour and depth images and locating files, for dataset loaders.

PNG and JPEG files are decoded by imagecodecs (libpng, libjpeg-turbo: docs/dependencies.md,
"Image decoding", says why), every other format, and any
file imagecodecs does not decode to the pixels expected, by Pillow. Every failure (missing file,
truncated or corrupt data, wrong pixel format) raises `slamkit.errors.DataError` with one line
naming the file and what was expected (Pillow's reading names it).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

# Image.open imports the plugin of a file's format at its first file: with the mapping thread
# running that import cost a real-time run's first frame 0.1 s (the stream's rate 2 % lower)
from PIL import Image, JpegImagePlugin, PngImagePlugin  # noqa: F401

from slamkit.errors import DataError

try:
    import imagecodecs
except ImportError:  # Python 3.10 (imagecodecs 2026 needs 3.11): Pillow decodes everything
    imagecodecs = None

_DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I", "F")
_JPEG_END = b"\xff\xd9"  # the end-of-image marker


def _decoded(path: Path, channels: int, dtype: type) -> np.ndarray | None:
    """The PNG or JPEG at `path` decoded by imagecodecs when it gives an HxW (channels 0) or
    HxWxchannels array of `dtype`; None otherwise (not installed, another format, an image of
    other pixels, or a file it cannot decode), and Pillow's reading then converts it or names
    the problem."""
    suffix = path.suffix.lower()
    if imagecodecs is None or suffix not in (".png", ".jpg", ".jpeg"):
        return None
    try:
        data = path.read_bytes()
        if suffix != ".png" and not data.endswith(_JPEG_END):
            return None  # libjpeg-turbo pads a truncated JPEG with grey where Pillow refuses it
        image = imagecodecs.png_decode(data) if suffix == ".png" else imagecodecs.jpeg8_decode(data)
    except (OSError, RuntimeError, ValueError):
        return None
    shape_ok = image.ndim == 2 if channels == 0 else image.ndim == 3 and image.shape[2] == channels
    return image if shape_ok and image.dtype == dtype else None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, FileNotFoundError):
        return "file not found"
    if isinstance(exc, IsADirectoryError):
        return "is a folder"
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _open(path: Path, what: str, expected: str, decode: bool = True) -> Image.Image:
    """Open (and decode) `path`, turning every Pillow / OS failure into a DataError."""
    try:
        im = Image.open(path)
        if decode:
            im.load()
        return im
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise DataError(f"cannot read {what} image {path}: {_reason(exc)} (expected {expected})") from None


def checked_rgb(path: str | Path) -> tuple[tuple[int, int], np.ndarray | Callable[[], np.ndarray]]:
    """((width, height), the HxWx3 uint8 image or a function that decodes it) of the colour
    image at `path`. A PNG is checked here without decoding its pixels (header, pixel mode and
    every chunk's checksum, up to IEND: a missing, truncated or corrupted file fails here, for a
    fraction of a decode's cost) and decoded by the function (`read_rgb`), so
    a frame whose colour nothing reads (a non-keyframe in real time) costs no decoding; other
    formats are decoded here."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        rgb = read_rgb(path)
        return (rgb.shape[1], rgb.shape[0]), rgb
    with _open(path, "colour", "an 8-bit colour image", decode=False) as im:
        if im.mode in _DEPTH_MODES:
            raise DataError(f"cannot read colour image {path}: pixel mode {im.mode} (expected an 8-bit colour image)")
        size = im.size
        try:
            im.verify()
        except (OSError, ValueError, SyntaxError) as exc:
            raise DataError(f"cannot read colour image {path}: {_reason(exc)} "
                            "(expected an 8-bit colour image)") from None
    return size, functools.partial(read_rgb, path)


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) in pixels from the image header only (no decoding)."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError, SyntaxError) as exc:
        raise DataError(f"cannot read image {path}: {_reason(exc)} (expected a PNG or JPEG image)") from None


def read_rgb(path: str | Path) -> np.ndarray:
    """HxWx3 uint8 RGB image. Grey, palette and RGBA images are converted to RGB."""
    path = Path(path)
    rgb = _decoded(path, 3, np.uint8)
    if rgb is not None:
        return rgb
    im = _open(path, "colour", "an 8-bit colour image")
    if im.mode in _DEPTH_MODES:
        raise DataError(f"cannot read colour image {path}: pixel mode {im.mode} (expected an 8-bit colour image)")
    if im.mode != "RGB":
        im = im.convert("RGB")
    return np.asarray(im, dtype=np.uint8).copy()


#: The depth a sensor sees: an image whose median valid depth lies outside this range (metres)
#: was read in the wrong unit (a depth scale that is not the file's, metres cast to uint16).
PLAUSIBLE_DEPTH_M = (0.05, 100.0)
#: Valid pixels an image needs for its unit to be judged (fewer: a blank view, not judged).
MIN_JUDGED_PIXELS = 100


def read_depth(path: str | Path, scale: float, invalid_values: Iterable[float] = (),
               size: tuple[int, int] | None = None) -> np.ndarray:
    """HxW float32 depth in metres. A 16-bit PNG (modes I;16 / I) holds raw units: raw / `scale`
    (e.g. 5000 for TUM, 1000 for millimetres); a 32-bit float image (mode F) holds metres, its
    own unit whatever `scale` is (as ROS's 32FC1 and float depth files do).

    Raw 0 stays 0 (invalid); raw values listed in `invalid_values` (e.g. 65535 in 7-Scenes, for
    integer images), negative values and non-finite values also become 0. An image whose depth
    is implausible in that unit (`PLAUSIBLE_DEPTH_M`: a scale that is not the file's, metres cast
    to integers, millimetres in a float file) is a one-line DataError naming the file, as is one
    that is not `size` (width, height: its colour image's), when given."""
    path = Path(path)
    raw = _decoded(path, 0, np.uint16)
    if raw is None:
        im = _open(path, "depth", "a 16-bit PNG")
        if im.mode not in _DEPTH_MODES:
            raise DataError(f"cannot read depth image {path}: pixel mode {im.mode} (expected a 16-bit PNG)")
        raw = np.asarray(im)
    if size is not None:
        check_same_size(size, raw, path)
    floating = raw.dtype.kind == "f"
    depth = raw.astype(np.float32)
    if floating:
        depth[~np.isfinite(raw) | (raw <= 0)] = 0.0
    else:
        np.divide(depth, np.float32(scale), out=depth)  # raw 0 is 0 m (invalid)
        if raw.dtype.kind != "u":
            depth[raw <= 0] = 0.0
        for v in invalid_values:
            depth[raw == v] = 0.0
    _check_plausible(path, depth, "a float image, read as metres" if floating else
                     f"{raw.dtype.itemsize * 8}-bit raw units / depth scale {scale:g}")
    return depth


def _check_plausible(path: Path, depth: np.ndarray, unit: str) -> None:
    """DataError when the median valid depth (of every 4th pixel) is outside PLAUSIBLE_DEPTH_M."""
    sample = depth[::4, ::4]
    valid = sample[sample > 0]
    if valid.size < MIN_JUDGED_PIXELS:
        return
    median = float(np.median(valid))
    low, high = PLAUSIBLE_DEPTH_M
    if not low <= median <= high:
        raise DataError(f"depth image {path}: median depth {median:.4g} m ({unit}), expected {low:g} to {high:g} m "
                        "(check dataset.depth_scale, or the unit the images were written in)")


def _size(image_or_size: np.ndarray | tuple[int, int]) -> tuple[int, int]:
    """(width, height) of an HxW(xC) image array, or the (width, height) given."""
    if isinstance(image_or_size, np.ndarray):
        return image_or_size.shape[1], image_or_size.shape[0]
    return tuple(image_or_size)


def check_same_size(rgb: np.ndarray | tuple[int, int], depth: np.ndarray, path: str | Path) -> None:
    """Raise DataError naming the depth file `path` if `depth` is not the size of the colour
    image (`rgb`: the image, or its (width, height))."""
    (w, h), (dh, dw) = _size(rgb), depth.shape[:2]
    if (w, h) != (dw, dh):
        raise DataError(f"depth image {path} is {dw}x{dh} but its colour image is {w}x{h} (expected the same size)")


def check_camera_size(rgb: np.ndarray | tuple[int, int], camera, path: str | Path) -> None:
    """Raise DataError naming the colour file `path` if the image (`rgb`: the image, or its
    (width, height)) is not `camera`'s size."""
    w, h = _size(rgb)
    if (w, h) != (camera.width, camera.height):
        raise DataError(
            f"colour image {path} is {w}x{h} but the camera is {camera.width}x{camera.height} "
            "(expected images of the camera's size)"
        )


def read_rgbd(rgb_path, depth_path, depth_scale: float, camera, invalid_values: Iterable[float] = ()):
    """One frame's colour, HxWx3 uint8 or, for a PNG, a function that decodes it (`checked_rgb`;
    `Frame.rgb` takes either), and depth (HxW float32 metres), both checked against the
    camera's size; every problem is a one-line DataError naming the file."""
    size, rgb = checked_rgb(rgb_path)
    check_camera_size(size, camera, rgb_path)
    depth = read_depth(depth_path, depth_scale, invalid_values, size)
    return rgb, depth


def dataset_folder(path: str | Path, expected: str, *markers: str) -> Path:
    """`path` as a folder holding each file in `markers`; DataError naming what is missing."""
    if not str(path):
        raise DataError(f"dataset.path is empty (expected {expected})")
    root = Path(path).expanduser()
    if not root.is_dir():
        raise DataError(f"dataset folder {root} not found (expected {expected})")
    for m in markers:
        if not (root / m).is_file():
            raise DataError(f"{root / m} not found (expected {expected})")
    return root


def find_ground_truth(root: Path, gt_path: str | Path | None, default: str) -> Path | None:
    """The ground-truth file of a dataset folder `root`: `gt_path` if given (a relative path is
    looked up in `root` first, then the working directory), else `root / default`. Returns None
    when the default file is absent (the caller warns); a given `gt_path` that does not exist
    raises DataError."""
    if gt_path is None:
        p = root / default
        return p if p.is_file() else None
    p = Path(gt_path).expanduser()
    if not p.is_absolute() and (root / p).is_file():
        p = root / p
    if not p.is_file():
        raise DataError(f"dataset.gt_path: {p} not found (expected a ground-truth trajectory file)")
    return p
