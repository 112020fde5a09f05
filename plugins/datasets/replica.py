"""Replica sequences in the NICE-SLAM rendering layout.

A folder holding ``results/frame%06d.jpg`` (colour), ``results/depth%06d.png`` (16-bit,
depth / 6553.5 = metres), ``traj.txt`` (one camera-to-world 4x4 pose per line, 16 numbers
row-major, metres; line k is frame k) and optionally ``cam_params.json`` (looked up in the
folder, then its parent as NICE-SLAM ships it; ``camera.w h fx fy cx cy scale``). Frame
timestamps are the frame numbers.
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
from slamkit.formats.images import dataset_folder, find_ground_truth, read_rgbd
from slamkit.formats.tum import read_float_table
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Dataset, DatasetConfig, DatasetTuning, RunContext, require
from slamkit.types import Camera, Frame

log = logging.getLogger(__name__)

DEFAULT_CAMERA = Camera(1200, 680, 600.0, 600.0, 599.5, 339.5)


@dataclass
class ReplicaConfig(DatasetConfig):
    """Options of a Replica sequence in the NICE-SLAM layout."""

    #: raw depth units per metre (cam_params.json's camera.scale wins when present)
    depth_scale: float = 6553.5
    #: pose file, relative paths looked up in `path` first (null: traj.txt if present)
    gt_path: str | None = None

    def validate(self) -> None:
        super().validate()
        require(self.depth_scale > 0, "dataset.depth_scale", "> 0 raw units per metre", self.depth_scale)


def read_cam_params(path: Path) -> tuple[Camera, float | None]:
    """(camera, depth scale or None) from a NICE-SLAM cam_params.json."""
    try:
        cam = json.loads(path.read_text())["camera"]
        c = Camera(int(cam["w"]), int(cam["h"]), float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]))
        scale = float(cam["scale"]) if "scale" in cam else None
    except (OSError, ValueError, KeyError, TypeError, OverflowError) as exc:
        first_line = (str(exc).splitlines() or [type(exc).__name__])[0]
        reason = f"missing key {exc}" if isinstance(exc, KeyError) else first_line
        expected = '{"camera": {w, h, fx, fy, cx, cy, scale}}'
        raise DataError(f"cannot read {path}: {reason} (expected {expected})") from None
    for name, expected in c.implausible():
        raise DataError(f"{path}: camera {name} = {getattr(c, name)!r} (expected {expected})")
    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise DataError(f"{path}: camera scale = {scale!r} (expected a finite number > 0 of raw units per metre)")
    return c, scale


class ReplicaDataset(Dataset):
    """Replica (NICE-SLAM layout). Depth in metres; gt_pose camera-to-world from traj.txt."""

    # rendered, noiseless depth of 1200x680 frames: the reference code's Replica settings
    default_tuning = DatasetTuning(depth_trunc=12.0, max_gaussian_scale=0.25,
                                   tracking_pixel_stride=10, correspondence_distance=0.02,
                                   new_gaussian_overlap=5e-5, keyframe_overlap=5e-4, keyframe_threshold=0.7,
                                   target_min_opacity=0.05)

    def __init__(self, cfg: ReplicaConfig, context: RunContext = RunContext()):
        super().__init__(cfg)
        expected = "a Replica folder in the NICE-SLAM layout: results/frame%06d.jpg, results/depth%06d.png, traj.txt"
        self.root = dataset_folder(cfg.path, expected)
        results = self.root / "results"
        matches = (re.fullmatch(r"frame(\d+)\.jpg", p.name) for p in results.glob("frame*.jpg"))
        numbers = sorted(int(m.group(1)) for m in matches if m)
        if not numbers:
            raise DataError(f"no colour frames {results}/frame%06d.jpg (expected {expected})")
        self.numbers = np.array(numbers)
        self.rgb_files = [results / f"frame{n:06d}.jpg" for n in numbers]
        self.depth_files = [results / f"depth{n:06d}.png" for n in numbers]
        missing = [p for p in self.depth_files if not p.is_file()]
        if missing:
            raise DataError(f"depth image {missing[0]} not found (expected one depth%06d.png per frame%06d.jpg)")

        self._camera, self.depth_scale = DEFAULT_CAMERA, cfg.depth_scale
        candidates = (self.root / "cam_params.json", self.root.parent / "cam_params.json")
        params = next((p for p in candidates if p.is_file()), None)
        if params is not None:
            self._camera, scale = read_cam_params(params)
            self.depth_scale = scale if scale is not None else cfg.depth_scale
        self.default_tuning = dataclasses.replace(self.default_tuning, depth_scale=self.depth_scale)

        self.gt_poses = None
        gt_file = find_ground_truth(self.root, cfg.gt_path, "traj.txt")
        if gt_file is None:
            log.warning("no ground truth: %s not found; the sequence runs without it", self.root / "traj.txt")
        else:
            table = read_float_table(gt_file, 16, "16 numbers: a row-major 4x4 camera-to-world pose")
            if len(table) <= self.numbers[-1]:
                raise DataError(
                    f"{gt_file} has {len(table)} poses but results/ goes up to frame {self.numbers[-1]} "
                    "(expected one pose line per frame)"
                )
            poses = table.reshape(-1, 4, 4)
            bad = np.flatnonzero(np.abs(poses[:, 3] - [0, 0, 0, 1]).max(axis=1) > 1e-6)
            if len(bad):
                raise DataError(
                    f"{gt_file}: the pose of frame {bad[0]} has a last row other than 0 0 0 1 "
                    "(expected a 4x4 rigid pose)"
                )
            self.gt_poses = poses[self.numbers]

    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return len(self.numbers)

    def raw_timestamp(self, raw_index: int) -> float:
        return float(raw_index)

    def load(self, raw_index: int) -> Frame:
        rgb, depth = read_rgbd(self.rgb_files[raw_index], self.depth_files[raw_index], self.depth_scale, self._camera)
        gt = None if self.gt_poses is None else self.gt_poses[raw_index].copy()
        return Frame(raw_index, float(self.numbers[raw_index]), rgb, depth, self._camera, gt)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("replica", ReplicaDataset, ReplicaConfig)]
