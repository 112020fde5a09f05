"""7-Scenes / 3DMatch per-frame layout.

One sequence folder (e.g. ``chess/seq-01``) holding, per frame, ``frame-%06d.color.jpg`` or
``.png``, ``frame-%06d.depth.png`` (16-bit millimetres; 0 and 65535 are invalid) and
optionally ``frame-%06d.pose.txt`` (4x4 camera-to-world, metres; a frame without one has no
ground truth). ``camera-intrinsics.txt`` (3x3 K, pixels) is looked up in the folder, then its
parent (3DMatch keeps it next to the seq-* folders); without it the 7-Scenes Kinect defaults
fx = fy = 585, cx = 320, cy = 240 apply. The image size is read from the first colour image.

Only the given folder is read: for a scene with several seq-NN subfolders, point
``dataset.path`` at one of them. Frame timestamps are the frame numbers.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.formats.images import dataset_folder, image_size, read_rgbd
from slamkit.formats.tum import read_float_table
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Dataset, DatasetConfig, DatasetTuning, RunContext, require
from slamkit.types import Camera, Frame

log = logging.getLogger(__name__)

DEFAULT_K = (585.0, 585.0, 320.0, 240.0)
INVALID_DEPTH = (65535,)


@dataclass
class SevenScenesConfig(DatasetConfig):
    """Options of a 7-Scenes / 3DMatch sequence."""

    #: raw depth units per metre (1000: millimetres)
    depth_scale: float = 1000.0

    def validate(self) -> None:
        super().validate()
        require(self.depth_scale > 0, "dataset.depth_scale", "> 0 raw units per metre", self.depth_scale)


def read_pose_file(path: Path) -> np.ndarray:
    """4x4 float64 camera-to-world pose from a 7-Scenes frame-%06d.pose.txt."""
    expected = "a 4x4 camera-to-world matrix: 4 rows of 4 finite numbers"
    T = read_float_table(path, 4, expected)
    if T.shape != (4, 4):
        raise DataError(f"{path}: {len(T)} rows (expected {expected})")
    return T


def read_intrinsics(path: Path) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels from a camera-intrinsics.txt holding a 3x3 K."""
    K = read_float_table(path, 3, "a 3x3 intrinsic matrix: 3 rows of 3 numbers")
    if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataError(f"{path}: not a 3x3 intrinsic matrix with positive focal lengths")
    return K[0, 0], K[1, 1], K[0, 2], K[1, 2]


class SevenScenesDataset(Dataset):
    """7-Scenes / 3DMatch sequence. Depth in metres (0 = invalid); gt_pose camera-to-world."""

    # a Kinect v1, like TUM's (depth_scale: the config's), whose colour and depth images come from
    # two cameras never registered to each other (docs/datasets.md, "Colour against depth")
    default_tuning = DatasetTuning(depth_trunc=4.0, colour_registered=False)

    def __init__(self, cfg: SevenScenesConfig, context: RunContext = RunContext()):
        super().__init__(cfg)
        self.default_tuning = dataclasses.replace(self.default_tuning, depth_scale=cfg.depth_scale)
        expected = "a 7-Scenes sequence folder with frame-%06d.color.(jpg|png) and frame-%06d.depth.png"
        self.root = dataset_folder(cfg.path, expected)
        colour = {}
        for p in self.root.glob("frame-*.color.*"):
            m = re.fullmatch(r"frame-(\d+)\.color\.(jpg|png)", p.name)
            if m:
                colour.setdefault(int(m.group(1)), p)
        if not colour:
            seqs = sorted(p.name for p in self.root.glob("seq-*") if p.is_dir())
            listed = ", ".join(seqs[:3]) + (", ..." if len(seqs) > 3 else "")
            hint = f"; it has {listed}: set dataset.path to one of them" if seqs else ""
            raise DataError(f"no frame-%06d.color.(jpg|png) in {self.root} (expected {expected}){hint}")
        self.numbers = np.array(sorted(colour))
        self.rgb_files = [colour[n] for n in self.numbers]
        self.depth_files = [self.root / f"frame-{n:06d}.depth.png" for n in self.numbers]
        self.pose_files = [self.root / f"frame-{n:06d}.pose.txt" for n in self.numbers]
        missing = [p for p in self.depth_files if not p.is_file()]
        if missing:
            raise DataError(f"depth image {missing[0]} not found (expected one frame-%06d.depth.png per colour frame)")

        candidates = (self.root / "camera-intrinsics.txt", self.root.parent / "camera-intrinsics.txt")
        k_file = next((p for p in candidates if p.is_file()), None)
        fx, fy, cx, cy = read_intrinsics(k_file) if k_file is not None else DEFAULT_K
        w, h = image_size(self.rgb_files[0])
        self._camera = Camera(w, h, fx, fy, cx, cy)
        if not any(p.is_file() for p in self.pose_files):
            log.warning("no ground truth: no frame-%%06d.pose.txt in %s; the sequence runs without it", self.root)

    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return len(self.numbers)

    def raw_timestamp(self, raw_index: int) -> float:
        return float(self.numbers[raw_index])  # the frame number, as `load` gives it

    def load(self, raw_index: int) -> Frame:
        rgb, depth = read_rgbd(self.rgb_files[raw_index], self.depth_files[raw_index], self.cfg.depth_scale,
                               self._camera, INVALID_DEPTH)
        pose_file = self.pose_files[raw_index]
        gt = read_pose_file(pose_file) if pose_file.is_file() else None
        return Frame(raw_index, float(self.numbers[raw_index]), rgb, depth, self._camera, gt)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("sevenscenes", SevenScenesDataset, SevenScenesConfig)]
