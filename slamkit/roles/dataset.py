"""The dataset role: a finite RGB-D sequence with random access, and what it knows of its sensor
and scenes (`slamkit.tuning.DatasetTuning`)."""

from __future__ import annotations

import dataclasses
import enum
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

from slamkit.config import PluginConfig, require, unlimited
from slamkit.errors import DataError
from slamkit.tuning import DatasetTuning
from slamkit.types import Camera, Frame

#: What a frame that fails to load does: stop the run (raise) or become a lost frame (skip).
#: (Functional form: `raise` is a keyword, and Hydra matches enum members by name.)
OnError = enum.Enum("OnError", {"raise": "raise", "skip": "skip"}, module=__name__)


@dataclass
class DatasetConfig(PluginConfig):
    """Options every dataset takes."""

    #: folder of the sequence
    path: str = ""
    #: the first raw frame used (frame i of the run is raw frame start + i * stride)
    start: int = 0
    #: use every stride-th raw frame
    stride: int = 1
    #: frames of the run, counting all passes (null: all)
    max_frames: int | None = None
    #: play the frames this many times, back and forth (a continuous path that revisits the scene)
    passes: int = 1
    #: metres; depth beyond is not used for tracking (null: the dataset's default)
    depth_trunc: float | None = unlimited(None)
    #: pixels; focal length override (null: the dataset's)
    fx: float | None = None
    #: pixels; focal length override (null: the dataset's)
    fy: float | None = None
    #: pixels; principal point override (null: the dataset's)
    cx: float | None = None
    #: pixels; principal point override (null: the dataset's)
    cy: float | None = None
    #: frames read ahead in a background thread (0: none)
    prefetch: int = 8
    #: a frame that cannot be read: raise stops the run naming the file; skip makes it a lost frame
    on_error: OnError = OnError["raise"]

    def live(self) -> bool:
        """Whether this config opens a source that does not wait for the run (a camera): it then
        runs in real time with realtime.drop_frames unless the command line says otherwise
        (`slamkit.registry.schema.validate_config`). The default: a recording, False."""
        return False

    def validate(self) -> None:
        require(self.start >= 0, "dataset.start", "an integer >= 0", self.start)
        require(self.stride >= 1, "dataset.stride", "an integer >= 1", self.stride)
        require(self.max_frames is None or self.max_frames >= 1, "dataset.max_frames", "null or >= 1", self.max_frames)
        require(self.passes >= 1, "dataset.passes", "an integer >= 1", self.passes)
        require(self.depth_trunc is None or self.depth_trunc > 0, "dataset.depth_trunc", "null or > 0 metres",
                self.depth_trunc)
        require(self.prefetch >= 0, "dataset.prefetch", "an integer >= 0", self.prefetch)
        for name in ("fx", "fy"):
            v = getattr(self, name)
            require(v is None or v > 0, f"dataset.{name}", "null or > 0 pixels", v)
        for name in ("cx", "cy"):
            v = getattr(self, name)
            require(v is None or v >= 0, f"dataset.{name}", "null or >= 0 pixels", v)


class SourceEnded(Exception):
    """Raised by a live source's `load(i)` when it has no frame i and never will (a recording
    played at its recorded pace has reached its end): the run's stream ends there, as a
    recording's ends after its last frame."""


class BackAndForth(Sequence[int]):
    """`passes` passes over the raw frames `one`, forward, backward, forward, ... (the frame at
    each turn once), cut at `limit` frames (None: all). Computed per index, so that a huge
    `dataset.passes` costs no memory."""

    def __init__(self, one: range, passes: int, limit: int | None):
        self.one = one
        total = len(one) + (passes - 1) * (len(one) - 1)
        self.length = total if limit is None else min(total, limit)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(self.length))]
        if i < 0:
            i += self.length
        if not 0 <= i < self.length:
            raise IndexError(i)
        period = 2 * (len(self.one) - 1)
        k = i % period
        return self.one[k if k < len(self.one) else period - k]


class Dataset(ABC):
    """A finite RGB-D sequence with random access.

    Subclasses set `native_camera` (before intrinsics overrides) and implement `num_available`
    and `load`; the base class applies start / stride / max_frames, intrinsics overrides and
    depth_trunc. `default_tuning` describes the sensor and scenes (a class attribute, or an
    instance attribute when it depends on the files, e.g. their depth scale); `tuning` is it
    with the user's depth_trunc applied. A dataset is the first plugin a run builds, from its
    config alone: the run's context (`slamkit.config.RunContext`) holds its tuning.
    """

    default_tuning: DatasetTuning = DatasetTuning()

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
    def live(self) -> bool:
        """A source that does not wait for the run (a camera, `DatasetConfig.live`): frame i
        arrives on its own clock (`arrival`), and a frame the run has passed may not be read again."""
        return False

    def arrival(self, i: int) -> float | None:
        """A live source: time.perf_counter() seconds when frame i arrived, None while it has not;
        the run drops frame i when frame i + 1 has arrived (realtime.drop_frames). A recording: None (the
        run paces it with realtime.fps_limit)."""
        return None

    def close(self) -> None:
        """Release what the dataset holds open (files, a camera's stream, a recording being
        written); the run calls it once its outputs are written. Again is a no-op."""

    @property
    def camera(self) -> Camera:
        c = self.cfg
        return self.native_camera.with_overrides(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy)

    def check_camera(self) -> None:
        """Check the run's intrinsics against the image size (`Camera.implausible`): a
        ConfigError naming `dataset.KEY` for an override, a DataError for the dataset's own."""
        camera = self.camera
        for name, expected in camera.implausible():
            value = getattr(camera, name)
            require(getattr(self.cfg, name, None) is None, f"dataset.{name}", expected, value)
            raise DataError(f"dataset at {self.cfg.path or '(built in)'}: camera {name} = {value!r} "
                            f"(expected {expected})")

    @property
    def tuning(self) -> DatasetTuning:
        """What other parts read for their settings left null (`default_tuning`, with
        `dataset.depth_trunc`)."""
        if self.cfg.depth_trunc is None:
            return self.default_tuning
        return dataclasses.replace(self.default_tuning, depth_trunc=float(self.cfg.depth_trunc))

    @property
    def depth_trunc(self) -> float:
        """Metres; depth beyond is not used for tracking (inf = no limit)."""
        return self.tuning.depth_trunc

    def raw_timestamp(self, raw_index: int) -> float:
        """Seconds; must not read image files (used for frames that fail to load). Datasets
        whose timestamps are not raw_index / 30 override it."""
        return raw_index / 30.0

    def timestamp(self, i: int) -> float:
        """Seconds of frame i of the run (with several passes: the first frame's, plus i mean
        frame periods of the selected frames)."""
        if self.cfg.passes == 1:
            return self.raw_timestamp(self.raw_indices()[i])
        one = range(self.cfg.start, self.num_available(), self.cfg.stride)
        first = self.raw_timestamp(one[0])
        period = (self.raw_timestamp(one[-1]) - first) / (len(one) - 1) if len(one) > 1 else 1 / 30.0
        return first + i * period

    def raw_indices(self) -> Sequence[int]:
        """The raw frame of each frame of the run (see DatasetConfig: start, stride, passes,
        max_frames)."""
        one = range(self.cfg.start, self.num_available(), self.cfg.stride)
        if self.cfg.passes > 1 and len(one) > 1:
            return BackAndForth(one, self.cfg.passes, self.cfg.max_frames)
        return one if self.cfg.max_frames is None else one[: self.cfg.max_frames]

    def __len__(self) -> int:
        return len(self.raw_indices())

    def __getitem__(self, i: int) -> Frame:
        raw = self.raw_indices()[i]
        frame = self.load(raw)
        frame.index = i
        if self.cfg.passes > 1:
            frame.timestamp = self.timestamp(i)
        frame.camera = self.camera
        frame.depth_trunc = self.depth_trunc
        return frame
