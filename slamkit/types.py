"""Core value types shared by every role.

Conventions used everywhere in slamkit:
- A pose is a 4x4 float64 numpy array, camera-to-world, OpenCV camera axes
  (x right, y down, z forward), translation in metres.
- Depth is in metres; 0 marks an invalid pixel.
- Quaternions are (w, x, y, z) inside slamkit; the TUM file format's (x, y, z, w) appears only
  in the trajectory reader and writer.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: image size in pixels, focal lengths and principal point in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    #: Degrees: the narrowest and the widest field of view a pinhole camera's focal length may give.
    FIELD_OF_VIEW_DEG = (1.0, 170.0)

    def implausible(self) -> list[tuple[str, str]]:
        """(field, what was expected) for each intrinsic outside sensible bounds for the image
        size: a positive whole size; fx and fy giving a field of view from 1 to 170 degrees
        across the width and the height; the principal point (cx, cy) inside the image. Empty
        when the camera is plausible."""
        found = []
        for name, size in (("width", self.width), ("height", self.height)):
            if not (isinstance(size, (int, np.integer)) and size > 0):
                found.append((name, "a whole number of pixels > 0"))
        if found:
            return found
        narrow, wide = (math.radians(d) / 2 for d in self.FIELD_OF_VIEW_DEG)
        for name, focal, size, axis in (("fx", self.fx, self.width, "wide"), ("fy", self.fy, self.height, "high")):
            low, high = size / (2 * math.tan(wide)), size / (2 * math.tan(narrow))
            if not low <= focal <= high:  # NaN fails too
                found.append((name, f"{low:.4g} to {high:.4g} pixels for an image {size} pixels {axis}, "
                                    f"a field of view of {self.FIELD_OF_VIEW_DEG[0]:g} to "
                                    f"{self.FIELD_OF_VIEW_DEG[1]:g} degrees"))
        for name, centre, size, axis in (("cx", self.cx, self.width, "wide"), ("cy", self.cy, self.height, "high")):
            if not 0 <= centre <= size:
                found.append((name, f"0 to {size} pixels, inside an image {size} pixels {axis}"))
        return found

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (pixel centres kept consistent)."""
        return Camera(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
        )

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "Camera":
        """The camera of the image's pixels [x0, x0 + width) x [y0, y0 + height): the principal
        point moved by (-x0, -y0) pixels, the focal lengths kept."""
        return Camera(width, height, self.fx, self.fy, self.cx - x0, self.cy - y0)

    def with_overrides(self, **values: float | None) -> "Camera":
        """A copy with the given non-None intrinsics replaced."""
        return replace(self, **{k: v for k, v in values.items() if v is not None})


class Deferred:
    """A dataclass field that may be given a zero-argument function instead of its value: the
    first read calls it and keeps what it returns, so work that only some frames need (decoding
    a colour image, rotating covariances to the world) is done only for those (keyframes in real
    time). Declared as `name: type = Deferred()` (no default) or `Deferred(default=value)`. Not
    locked: two threads reading a pending field at once may both compute it (one result is kept).
    """

    _NO_DEFAULT = object()
    _SLOT = "_deferred_{}"  # where an instance keeps a field's value or pending function

    class _Pending:
        __slots__ = ("compute",)

        def __init__(self, compute):
            self.compute = compute

    def __init__(self, default=_NO_DEFAULT):
        self.default = default

    def __set_name__(self, owner, name: str) -> None:
        self.name, self.slot = name, Deferred._SLOT.format(name)

    def __get__(self, obj, owner=None):
        if obj is None:  # the dataclass asks for the field's default
            if self.default is Deferred._NO_DEFAULT:
                raise AttributeError(self.name)
            return self.default
        try:
            value = obj.__dict__[self.slot]
        except KeyError:
            raise AttributeError(self.name) from None
        if isinstance(value, Deferred._Pending):
            value = obj.__dict__[self.slot] = value.compute()
        return value

    def __set__(self, obj, value) -> None:
        obj.__dict__[self.slot] = Deferred._Pending(value) if callable(value) else value

    @staticmethod
    def pending(obj, name: str):
        """The function that will compute `obj`'s field `name` when first read, or None when
        the field holds a value (or is not a Deferred field)."""
        value = obj.__dict__.get(Deferred._SLOT.format(name))
        return value.compute if isinstance(value, Deferred._Pending) else None


@dataclass
class Frame:
    """One RGB-D frame.

    rgb: HxWx3 uint8 (a dataset may give a function that decodes it: see Deferred). depth: HxW
    float32 metres, 0 = invalid. gt_pose: camera-to-world 4x4 float64 or None. depth_trunc:
    metres; farther points are not used for tracking.
    """

    index: int
    timestamp: float
    rgb: np.ndarray = Deferred()
    depth: np.ndarray
    camera: Camera
    gt_pose: np.ndarray | None = None
    depth_trunc: float = float("inf")


class KeyframeKind(enum.Enum):
    """What a keyframe is used for (paper Sec. 3.3)."""

    NONE = "none"
    TRACKING = "tracking"          # changes the tracking target and adds Gaussians
    MAPPING_ONLY = "mapping_only"  # adds Gaussians and an image for mapping only

    def __bool__(self) -> bool:
        return self is not KeyframeKind.NONE


@dataclass
class FrameGaussians:
    """Gaussians made from one frame's points, in world coordinates.

    means: Nx3 metres (world). covariances: Nx3x3 m^2 (world, already regularised as the
    tracker uses them). shape_covariances: Nx3x3 m^2 (world), the raw covariances that give
    new map Gaussians their shape before scale alignment (None = use `covariances`; the
    reference code takes the raw k-NN eigenvalues here, not the regularised ones, whose median
    is 1 m^2). colors: Nx3 in [0, 1]. depths: N camera depths in metres (for scale
    alignment). trackable: N bool (inside depth_trunc). sq_dist_to_map: N squared distance in
    m^2 to the nearest map Gaussian found by the tracker's last correspondence search
    (inf where none was found). covariances, colors and shape_covariances may be given as
    functions computing them (Deferred): only a keyframe's Gaussians enter the map.
    """

    means: np.ndarray
    covariances: np.ndarray = Deferred()
    colors: np.ndarray = Deferred()
    depths: np.ndarray
    trackable: np.ndarray
    sq_dist_to_map: np.ndarray | None = None
    shape_covariances: np.ndarray | None = Deferred(default=None)

    def __len__(self) -> int:
        return len(self.means)


@dataclass
class TrackingResult:
    """What a tracker reports for one frame.

    pose: camera-to-world 4x4 float64. lost: the tracker could not estimate the pose and kept
    its prediction. correspondence_ratio: fraction of trackable frame points with a map
    Gaussians close by (None when the tracker has no such notion). gaussians: the frame's
    Gaussians, an optional hand-over (None: the map's growth makes a keyframe's from the frame
    at `pose`, `slamkit.map.growth.frame_gaussians`). stats: timings in seconds and
    counters for the per-frame log.
    """

    pose: np.ndarray
    lost: bool = False
    correspondence_ratio: float | None = None
    gaussians: FrameGaussians | None = None
    stats: dict[str, Any] = field(default_factory=dict)
