"""`dataset=folder`: your own RGB-D recording, as a folder of colour and depth images with an
intrinsics file (docs/datasets.md, "`folder`: your own recording", gives the layout).

A colour and a depth image with the same file stem form a frame, in sorted stem order; the
ground truth (camera-to-world, OpenCV axes, metres) is a TUM-format file (8 fields per line,
interpolated at the frame timestamps) or one row-major 4x4 pose per line (16 fields).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.formats.images import dataset_folder, image_size, read_rgbd
from slamkit.formats.tum import interpolate_poses, read_float_table, read_tum_trajectory
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Dataset, DatasetConfig, DatasetTuning, RunContext, require
from slamkit.types import Camera, Frame

log = logging.getLogger(__name__)

COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".png", ".tif", ".tiff")
INTRINSICS_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
INTRINSICS_EXPECTED = "fx, fy, cx, cy, width, height, depth_scale and optionally depth_trunc"
TRAJECTORY_EXPECTED = "8 fields 'timestamp tx ty tz qx qy qz qw' or 16 numbers, a row-major 4x4 pose, per line"


@dataclass
class FolderConfig(DatasetConfig):
    """Options of a folder recording."""

    #: the intrinsics file, relative to `path` or absolute (intrinsics.yml / .json are found too)
    intrinsics: str = "intrinsics.yaml"
    #: ground-truth file, relative to `path`, then the working directory (null: trajectory.txt if present)
    trajectory: str | None = None
    #: colour subfolder (null: color/, else rgb/)
    color_dir: str | None = None
    #: depth subfolder
    depth_dir: str = "depth"
    #: raw depth units per metre of 16-bit depth images (null: the intrinsics file's)
    depth_scale: float | None = None
    #: seconds between a frame and the nearest pose of a TUM-format trajectory
    gt_tolerance: float = 0.02

    def validate(self) -> None:
        super().validate()
        require(self.depth_scale is None or self.depth_scale > 0, "dataset.depth_scale",
                "null or > 0 raw units per metre", self.depth_scale)
        require(self.gt_tolerance > 0, "dataset.gt_tolerance", "> 0 seconds", self.gt_tolerance)


def read_intrinsics(path: Path, depth_scale: float | None = None) -> tuple[Camera, float, float | None]:
    """(camera, depth scale, depth_trunc or None) from a YAML or JSON intrinsics file;
    `depth_scale` (not None) replaces the file's, which may then be absent."""
    if not path.is_file():
        raise DataError(f"intrinsics file {path} not found (expected a YAML or JSON file with {INTRINSICS_EXPECTED})")
    try:
        text = path.read_text()
        if path.suffix.lower() == ".json":
            values = json.loads(text)
        else:
            import yaml

            values = yaml.safe_load(text)
    except Exception as exc:  # OSError, UnicodeDecodeError, JSON / YAML syntax errors
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        mark = getattr(exc, "problem_mark", None)  # YAML: say where
        if mark is not None:
            reason = f"{getattr(exc, 'problem', None) or reason} at line {mark.line + 1}"
        raise DataError(f"cannot read intrinsics file {path}: {reason}") from None
    if not isinstance(values, dict):
        raise DataError(f"intrinsics file {path}: not a mapping of keys to values (expected {INTRINSICS_EXPECTED})")
    if depth_scale is not None:
        values = {**values, "depth_scale": depth_scale}
    missing = [k for k in INTRINSICS_KEYS if k not in values]
    if missing:
        keys = "key" if len(missing) == 1 else "keys"
        raise DataError(f"intrinsics file {path}: missing {keys} {', '.join(missing)} (expected {INTRINSICS_EXPECTED})")
    numbers = {}
    for key in (*INTRINSICS_KEYS, "depth_trunc"):
        value = values.get(key)
        if key == "depth_trunc" and value is None:
            continue
        try:
            numbers[key] = float(value)
        except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond float's range
            raise DataError(f"intrinsics file {path}: {key} = {value!r} is not a number") from None
        positive = numbers[key] > 0 if key not in ("cx", "cy") else True
        if not (math.isfinite(numbers[key]) and positive):
            raise DataError(f"intrinsics file {path}: {key} = {value!r} (expected a finite positive number)")
    for key in ("width", "height"):
        if not numbers[key].is_integer():
            raise DataError(f"intrinsics file {path}: {key} = {values[key]!r} (expected a whole number of pixels)")
    camera = Camera(int(numbers["width"]), int(numbers["height"]),
                    numbers["fx"], numbers["fy"], numbers["cx"], numbers["cy"])
    for key, expected in camera.implausible():
        raise DataError(f"intrinsics file {path}: {key} = {values[key]!r} (expected {expected})")
    return camera, numbers["depth_scale"], numbers.get("depth_trunc")


def _sort_key(stem: str):
    """Natural order: 'frame2' before 'frame10'."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", stem)]


def _is_number(stem: str) -> bool:
    try:
        return math.isfinite(float(stem))
    except ValueError:
        return False


def list_images(folder: Path, suffixes: tuple[str, ...], what: str) -> dict[str, Path]:
    """stem -> file of the images in `folder` (by suffix, case-insensitive)."""
    if not folder.is_dir():
        raise DataError(f"{what} folder {folder} not found (expected a folder of {what} images)")
    found: dict[str, Path] = {}
    for p in folder.iterdir():
        if p.is_file() and p.suffix.lower() in suffixes:
            if p.stem in found:
                raise DataError(f"{what} images {found[p.stem].name} and {p.name} in {folder} have the same name "
                                "(expected one image per frame)")
            found[p.stem] = p
    if not found:
        raise DataError(f"no {what} images ({'/'.join(suffixes)}) in {folder}")
    return found


def _few(names: list[str], n: int = 3) -> str:
    return ", ".join(names[:n]) + (", ..." if len(names) > n else "")


class FolderDataset(Dataset):
    """A folder of colour + depth images with an intrinsics file (see the module docstring).
    Depth in metres; gt_pose camera-to-world or None."""

    def __init__(self, cfg: FolderConfig, context: RunContext = RunContext()):
        super().__init__(cfg)
        self.root = dataset_folder(cfg.path, "a folder with color/ (or rgb/), depth/ and an intrinsics file")
        self.intrinsics_file = self.root / cfg.intrinsics
        if cfg.intrinsics == FolderConfig.intrinsics and not self.intrinsics_file.is_file():
            others = (self.root / n for n in ("intrinsics.yml", "intrinsics.json"))
            self.intrinsics_file = next((p for p in others if p.is_file()), self.intrinsics_file)
        self._camera, self.depth_scale, depth_trunc = read_intrinsics(self.intrinsics_file, cfg.depth_scale)
        # a hand-held depth camera: the generic profile, with the intrinsics file's depth facts
        self.default_tuning = dataclasses.replace(
            DatasetTuning(), depth_scale=self.depth_scale,
            depth_trunc=depth_trunc if depth_trunc is not None else DatasetTuning.depth_trunc)

        default_color = next((d for d in ("color", "rgb") if (self.root / d).is_dir()), "color")
        color_dir = self.root / (cfg.color_dir or default_color)
        depth_dir = self.root / cfg.depth_dir
        colour = list_images(color_dir, COLOR_SUFFIXES, "colour")
        depth = list_images(depth_dir, DEPTH_SUFFIXES, "depth")
        no_depth = sorted(set(colour) - set(depth), key=_sort_key)
        no_colour = sorted(set(depth) - set(colour), key=_sort_key)
        if no_depth or no_colour:
            parts = []
            if no_depth:
                parts.append(f"{len(no_depth)} colour images in {color_dir} have no depth image ({_few(no_depth)})")
            if no_colour:
                parts.append(f"{len(no_colour)} depth images in {depth_dir} have no colour image ({_few(no_colour)})")
            raise DataError("; ".join(parts) + " (expected a colour and a depth image of the same name per frame)")
        numeric = all(_is_number(s) for s in colour)
        stems = sorted(colour, key=float if numeric else _sort_key)
        self.rgb_files = [colour[s] for s in stems]
        self.depth_files = [depth[s] for s in stems]
        self.timestamps = self._timestamps(stems, numeric)
        w, h = image_size(self.rgb_files[0])
        if (w, h) != (self._camera.width, self._camera.height):
            raise DataError(f"colour image {self.rgb_files[0]} is {w}x{h} but {self.intrinsics_file} says "
                            f"{self._camera.width}x{self._camera.height} (expected the images' size)")
        self.gt_poses = self._ground_truth()

    def _timestamps(self, stems: list[str], numeric: bool) -> np.ndarray:
        path = self.root / "timestamps.txt"
        if path.is_file():
            ts = read_float_table(path, 1, "one timestamp in seconds per line")[:, 0]
            if len(ts) != len(stems):
                raise DataError(f"{path} has {len(ts)} timestamps for {len(stems)} frames (expected one per frame)")
            return ts
        return np.array([float(s) for s in stems]) if numeric else np.arange(len(stems), dtype=np.float64)

    def _ground_truth(self) -> np.ndarray | None:
        """(N,4,4) camera-to-world poses (NaN where a frame has none), or None."""
        name = self.cfg.trajectory
        if name is None:
            path = self.root / "trajectory.txt"
            if not path.is_file():
                log.info("no ground truth: no trajectory.txt in %s (set dataset.trajectory)", self.root)
                return None
        else:
            path = Path(name).expanduser()
            if not path.is_absolute() and (self.root / path).is_file():
                path = self.root / path
            if not path.is_file():
                raise DataError(f"dataset.trajectory: {path} not found "
                                f"(expected a trajectory file: {TRAJECTORY_EXPECTED})")
        fields = next((len(line.replace(",", " ").split()) for line in _read_lines(path)), 0)
        if fields == 8:
            gt_ts, gt = read_tum_trajectory(path)
            poses = interpolate_poses(gt_ts, gt, self.timestamps, self.cfg.gt_tolerance)
            if not np.isfinite(poses).all(axis=(1, 2)).any():
                raise DataError(f"{path}: no pose within {self.cfg.gt_tolerance} s of any frame timestamp "
                                f"({self.timestamps[0]:.6f} .. {self.timestamps[-1]:.6f}; "
                                "expected the frames' timestamps)")
            return poses
        if fields == 16:
            poses = read_float_table(path, 16, "16 numbers: a row-major 4x4 camera-to-world pose").reshape(-1, 4, 4)
            if len(poses) != len(self.timestamps):
                raise DataError(f"{path} has {len(poses)} poses for {len(self.timestamps)} frames "
                                "(expected one line per frame)")
            bad = np.flatnonzero(np.abs(poses[:, 3] - [0, 0, 0, 1]).max(axis=1) > 1e-6)
            if len(bad):
                raise DataError(f"{path} line {bad[0] + 1}: last row is not 0 0 0 1 (expected a 4x4 rigid pose)")
            return poses
        raise DataError(f"{path}: {fields} fields on the first line (expected {TRAJECTORY_EXPECTED})")

    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return len(self.rgb_files)

    def raw_timestamp(self, raw_index: int) -> float:
        return float(self.timestamps[raw_index])

    def load(self, raw_index: int) -> Frame:
        rgb, depth = read_rgbd(self.rgb_files[raw_index], self.depth_files[raw_index], self.depth_scale, self._camera)
        gt = None
        if self.gt_poses is not None and np.isfinite(self.gt_poses[raw_index]).all():
            gt = self.gt_poses[raw_index].copy()
        return Frame(raw_index, float(self.timestamps[raw_index]), rgb, depth, self._camera, gt)


def _read_lines(path: Path):
    """The non-empty, non-comment lines of a text file."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read {path}: {(str(exc).splitlines() or [type(exc).__name__])[0]}") from None
    return (s for s in (line.strip() for line in text.splitlines()) if s and not s.startswith("#"))


@hookimpl
def slamkit_plugins():
    return [PluginSpec("folder", FolderDataset, FolderConfig)]
