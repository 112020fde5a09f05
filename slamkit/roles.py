"""The abstract roles a plugin can fill. Each is small on purpose.

A plugin provides a subclass of one role and a config dataclass; the registry builds the
subclass with the validated config object as its only argument.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from slamkit.errors import ConfigError
from slamkit.gaussian_map import GaussianMap
from slamkit.types import Camera, Frame, KeyframeKind, TrackingResult


@dataclass
class PluginConfig:
    """Base of every plugin's config dataclass. Subclasses add fields with defaults and may
    override `validate` to reject out-of-range values (raise ConfigError naming the field)."""

    def validate(self) -> None:
        """Raise ConfigError for an out-of-range value. The default checks nothing."""

    def __post_init__(self) -> None:
        self.validate()


def require(condition: bool, field: str, expected: str, value: Any) -> None:
    """Raise a one-line ConfigError unless `condition` holds."""
    if not condition:
        raise ConfigError(f"{field}: expected {expected}, got {value!r}")


#: What a frame that fails to load does: stop the run (raise) or become a lost frame (skip).
#: (Functional form: `raise` is a keyword, and Hydra matches enum members by name.)
OnError = enum.Enum("OnError", {"raise": "raise", "skip": "skip"}, module=__name__)


@dataclass
class DatasetConfig(PluginConfig):
    """Options every dataset takes.

    path: folder of the sequence. start, stride, max_frames: which frames are used (frame i of
    the run is raw frame start + i * stride); max_frames null = all. depth_trunc: metres,
    points beyond are not used for tracking (null = the dataset's default). fx, fy, cx, cy:
    override the intrinsics in pixels (null = from the dataset). prefetch: frames read ahead
    in a background thread. on_error: raise (default) stops the run at a frame that cannot be
    read, with a one-line error naming the file; skip logs a warning, marks the frame lost
    (it keeps the previous pose) and counts it in lost_frames.
    """

    path: str = ""
    start: int = 0
    stride: int = 1
    max_frames: int | None = None
    depth_trunc: float | None = None
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    prefetch: int = 8
    on_error: OnError = OnError["raise"]

    def validate(self) -> None:
        require(self.start >= 0, "dataset.start", "an integer >= 0", self.start)
        require(self.stride >= 1, "dataset.stride", "an integer >= 1", self.stride)
        require(self.max_frames is None or self.max_frames >= 1, "dataset.max_frames", "null or >= 1", self.max_frames)
        require(self.depth_trunc is None or self.depth_trunc > 0, "dataset.depth_trunc", "null or > 0 metres", self.depth_trunc)
        require(self.prefetch >= 0, "dataset.prefetch", "an integer >= 0", self.prefetch)
        for name in ("fx", "fy"):
            v = getattr(self, name)
            require(v is None or v > 0, f"dataset.{name}", "null or > 0 pixels", v)


class Dataset(ABC):
    """A finite RGB-D sequence with random access.

    Subclasses set `camera` (before intrinsics overrides) and implement `num_available` and
    `load`; the base class applies start / stride / max_frames, intrinsics overrides and
    depth_trunc. `hints` lets a dataset suggest per-dataset defaults to other roles (e.g.
    {"pixel_stride": 5}); a role's config value of null means "use the hint".
    """

    default_depth_trunc: float = float("inf")
    hints: dict[str, Any] = {}

    def __init__(self, cfg: DatasetConfig):
        self.cfg = cfg

    @property
    @abstractmethod
    def native_camera(self) -> Camera:
        """The dataset's own intrinsics."""

    @abstractmethod
    def num_available(self) -> int:
        """Number of frames in the sequence on disk."""

    @abstractmethod
    def load(self, raw_index: int) -> Frame:
        """Read raw frame `raw_index` (0-based over the whole sequence) from disk."""

    @property
    def camera(self) -> Camera:
        c = self.cfg
        return self.native_camera.with_overrides(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy)

    @property
    def depth_trunc(self) -> float:
        return self.cfg.depth_trunc if self.cfg.depth_trunc is not None else self.default_depth_trunc

    def raw_timestamp(self, raw_index: int) -> float:
        """Seconds; must not read image files (used for frames that fail to load). Datasets
        whose timestamps are not raw_index / 30 override it."""
        return raw_index / 30.0

    def timestamp(self, i: int) -> float:
        return self.raw_timestamp(self.raw_indices()[i])

    def raw_indices(self) -> range:
        r = range(self.cfg.start, self.num_available(), self.cfg.stride)
        return r if self.cfg.max_frames is None else r[: self.cfg.max_frames]

    def __len__(self) -> int:
        return len(self.raw_indices())

    def __getitem__(self, i: int) -> Frame:
        raw = self.raw_indices()[i]
        frame = self.load(raw)
        frame.index = i
        frame.camera = self.camera
        frame.depth_trunc = self.depth_trunc
        return frame


class Tracker(ABC):
    """Estimates each frame's camera-to-world pose."""

    @abstractmethod
    def track(self, frame: Frame, gaussian_map: GaussianMap) -> TrackingResult:
        """Pose of `frame` (camera-to-world). Must not raise on a bad frame: return
        `lost=True` with the predicted pose instead."""

    def update_target(self, gaussian_map: GaussianMap) -> None:
        """Called after a tracking keyframe added its Gaussians: rebuild what is aligned to."""

    def initialize(self, first_pose: np.ndarray) -> None:
        """Called once before the first frame with the pose the trajectory starts from."""


@dataclass
class KeyframeHistory:
    """Frame indices (`frame.index`) of the last tracking keyframe and of the last keyframe of
    any kind; None before the first. Policies count their intervals from these."""

    last_tracking: int | None = None
    last_keyframe: int | None = None

    def record(self, index: int, kind: KeyframeKind) -> KeyframeKind:
        """Note frame `index`'s decision and return it."""
        if kind is KeyframeKind.TRACKING:
            self.last_tracking = index
        if kind:
            self.last_keyframe = index
        return kind


class KeyframePolicy(ABC):
    """Decides which frames become keyframes, and of which kind."""

    @abstractmethod
    def decide(self, frame: Frame, result: TrackingResult) -> KeyframeKind:
        """The keyframe kind of `frame` given its tracking result."""


class KeyframeSampler(ABC):
    """Chooses which keyframe the mapper trains on next."""

    @abstractmethod
    def sample(
        self,
        keyframe_ids: list[int],
        current_pose: np.ndarray | None,
        rng: np.random.Generator,
        keyframe_poses: dict[int, np.ndarray] | None = None,
    ) -> int:
        """One of `keyframe_ids` (non-empty). current_pose and keyframe_poses (id -> pose) are
        camera-to-world 4x4; a sampler that needs no geometry ignores them."""


class Mapper(ABC):
    """Optimises the shared Gaussian map from keyframe images."""

    @abstractmethod
    def add_keyframe(self, frame: Frame, result: TrackingResult, kind: KeyframeKind, new_rows: slice) -> None:
        """Register a keyframe; `new_rows` are the map rows its Gaussians were added at."""

    @abstractmethod
    def optimize(self, iterations: int) -> int:
        """Run up to `iterations` optimisation steps; return how many were done."""

    def finish(self) -> None:
        """Called after the last frame (final iterations, if any)."""

    def evaluate(self, frames, poses: list[np.ndarray], out_dir) -> dict[str, Any]:
        """Rendering metrics (psnr, ssim, ...) for the run's metrics.json; {} if none."""
        return {}

    def bind(self, gaussian_map: GaussianMap) -> None:
        """Called once with the shared map before the first frame."""
        self.gaussian_map = gaussian_map

    def render_view(self, pose: np.ndarray, camera: Camera) -> RenderOutput | None:
        """The map as this mapper renders it from `pose` (4x4 camera-to-world, metres) for
        `camera`, without gradients (for viewers); None when the mapper cannot render (the
        default). Must be safe to call beside a mapping thread."""
        return None


from slamkit.rendering import Rasterizer, RenderOutput  # noqa: E402  (a role too; defined with its output type)


@dataclass
class ViewerConfig(PluginConfig):
    """Options every viewer takes (a viewer's config may derive from this one).

    render_every: frames between renders of the map from the current pose (0 = never; a
    render costs about one mapping step). render_scale: resolution of those renders relative
    to the frame's, in (0, 1]. map_every: frames between logs of the Gaussian centres (0 =
    only after the last frame). map_max_points: at most this many Gaussian centres per log
    (an even subsample of the map).
    """

    render_every: int = 10
    render_scale: float = 0.5
    map_every: int = 10
    map_max_points: int = 200_000

    def validate(self) -> None:
        require(self.render_every >= 0, "viewer.render_every", "an integer >= 0 (0 = never)", self.render_every)
        require(0 < self.render_scale <= 1, "viewer.render_scale", "in (0, 1]", self.render_scale)
        require(self.map_every >= 0, "viewer.map_every", "an integer >= 0 (0 = at the end only)", self.map_every)
        require(self.map_max_points >= 1, "viewer.map_max_points", "an integer >= 1", self.map_max_points)


@dataclass
class MapPoints:
    """Gaussian centres for display: positions (N,3) float32 world metres, colors (N,3) uint8
    RGB, radii (N,) float32 metres (the geometric mean of each Gaussian's standard deviations),
    out of `total` Gaussians in the map."""

    positions: np.ndarray
    colors: np.ndarray
    radii: np.ndarray
    total: int


@dataclass
class ViewerFrame:
    """What a viewer sees of one processed frame.

    frame: the input (rgb, depth in metres, camera, gt_pose camera-to-world or None). pose:
    the estimated camera-to-world pose (4x4, metres, OpenCV axes). keyframe, lost: the
    tracker's and keyframe policy's outcome. trajectory, gt_trajectory: (n,3) camera centres
    in world metres of the frames so far (gt: the frames that have ground truth). The map and
    the mapper are shared with the running SLAM: use `map_points` and `render`, which copy
    under the map's lock.
    """

    frame: Frame
    pose: np.ndarray
    keyframe: KeyframeKind
    lost: bool
    trajectory: np.ndarray
    gt_trajectory: np.ndarray
    gaussian_map: GaussianMap
    mapper: Mapper

    def map_points(self, max_points: int) -> MapPoints:
        """An even subsample (every k-th row) of at most `max_points` Gaussian centres."""
        gm = self.gaussian_map
        with gm.lock:
            total = len(gm)
            step = max(1, -(-total // max_points))
            means = gm.means.detach()[::step].cpu().numpy().astype(np.float32)
            colors = gm.colors.detach()[::step].clamp(0, 1).cpu().numpy()
            log_scales = gm.log_scales.detach()[::step].cpu().numpy()
        radii = np.exp(log_scales.mean(axis=1)).astype(np.float32) if len(log_scales) else np.zeros(0, np.float32)
        return MapPoints(means, (colors * 255 + 0.5).astype(np.uint8), radii, total)

    def render(self, scale: float = 1.0) -> RenderOutput | None:
        """The mapper's render from the estimated pose at `scale` of the frame's resolution,
        or None when the mapper cannot render."""
        camera = self.frame.camera if scale == 1.0 else self.frame.camera.scaled(scale)
        return self.mapper.render_view(self.pose, camera)


class Viewer(ABC):
    """Shows (or records) a run as it happens. Optional: `viewer=none` does nothing.

    slamkit calls `start` once before the first frame, `show` after every processed frame
    (in the tracking thread; keep it cheap, do expensive things every n-th frame) and `close`
    once at the end, also when the run stops early. An exception from any of them is reported
    as a warning and the viewer is switched off: a viewer never stops a run.
    """

    def start(self, camera: Camera, out_dir: Path) -> None:
        """Called before the first frame with the dataset's camera (pixels) and the run folder."""

    @abstractmethod
    def show(self, view: ViewerFrame) -> None:
        """Log one processed frame."""

    def close(self, view: ViewerFrame | None) -> None:
        """Called after the last frame with its view (None if no frame was processed)."""


ROLES: dict[str, type] = {
    "dataset": Dataset,
    "tracker": Tracker,
    "mapper": Mapper,
    "keyframe": KeyframePolicy,
    "sampler": KeyframeSampler,
    "rasterizer": Rasterizer,
    "viewer": Viewer,
}


def config_fields(cfg_cls: type) -> list[str]:
    return [f.name for f in fields(cfg_cls)]
