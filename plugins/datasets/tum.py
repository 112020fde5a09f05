"""TUM RGB-D sequences in their native layout.

A folder holding ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` lines, file names
relative to the folder), the images they list (colour PNG; 16-bit depth PNG, depth / 5000 =
metres) and optionally ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world,
metres). Colour frames are primary: each is paired with the nearest free depth frame within
`association_tolerance` seconds (as TUM's associate.py); colour frames without one are
dropped. Ground truth is interpolated at the colour timestamp.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.formats.images import dataset_folder, find_ground_truth, read_rgbd
from slamkit.formats.tum import associate, interpolate_poses, read_tum_list, read_tum_trajectory
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import Dataset, DatasetConfig, DatasetTuning, RunContext, require
from slamkit.types import Camera, Frame

log = logging.getLogger(__name__)

#: Intrinsics of the three TUM RGB-D sensors (pixels, 640x480), from the TUM benchmark page.
CAMERAS = {
    "fr1": Camera(640, 480, 517.3, 516.5, 318.6, 255.3),
    "fr2": Camera(640, 480, 520.9, 521.0, 325.1, 249.7),
    "fr3": Camera(640, 480, 535.4, 539.2, 320.1, 247.6),
}


@dataclass
class TUMConfig(DatasetConfig):
    """Options of a TUM RGB-D sequence."""

    #: seconds allowed between a colour frame and its depth frame
    association_tolerance: float = 0.02
    #: seconds allowed between a colour frame and its nearest ground-truth pose
    gt_tolerance: float = 0.02
    #: ground-truth file, relative paths looked up in `path` first (null: groundtruth.txt if present)
    gt_path: str | None = None
    #: raw depth units per metre of the 16-bit depth images
    depth_scale: float = 5000.0
    #: fr1 | fr2 | fr3 intrinsics (null: from the folder name, e.g. rgbd_dataset_freiburg2_xyz; fr1 if none)
    camera: str | None = None

    def validate(self) -> None:
        super().validate()
        tol = self.association_tolerance
        require(tol > 0, "dataset.association_tolerance", "> 0 seconds", tol)
        require(self.gt_tolerance > 0, "dataset.gt_tolerance", "> 0 seconds", self.gt_tolerance)
        require(self.depth_scale > 0, "dataset.depth_scale", "> 0 raw units per metre", self.depth_scale)
        require(self.camera in (None, *CAMERAS), "dataset.camera", "null, fr1, fr2 or fr3", self.camera)


def detect_camera(root: Path) -> str:
    """fr1 / fr2 / fr3 from the folder's name (or its parents'): 'freiburg2', 'fr2', ..."""
    for part in (root.resolve().name, *reversed(root.resolve().parent.parts)):
        m = re.search(r"(?:freiburg|fr)_?([123])(?!\d)", part.lower())
        if m:
            return f"fr{m.group(1)}"
    log.warning("cannot tell the TUM camera from the folder name %s; using fr1 intrinsics (set dataset.camera)", root)
    return "fr1"


class TUMDataset(Dataset):
    """TUM RGB-D sequence. Frame timestamps are the colour images' (seconds); depth in metres;
    gt_pose camera-to-world (None where ground truth does not cover the frame)."""

    default_tuning = DatasetTuning(depth_trunc=3.0)  # a Kinect v1 in an office (depth_scale: the config's)

    def __init__(self, cfg: TUMConfig, context: RunContext = RunContext()):
        super().__init__(cfg)
        self.default_tuning = dataclasses.replace(self.default_tuning, depth_scale=cfg.depth_scale)
        expected = "a TUM RGB-D folder with rgb.txt, depth.txt and their images"
        self.root = dataset_folder(cfg.path, expected, "rgb.txt", "depth.txt")
        rgb_ts, rgb_files = read_tum_list(self.root / "rgb.txt")
        depth_ts, depth_files = read_tum_list(self.root / "depth.txt")
        ia, ib = associate(rgb_ts, depth_ts, cfg.association_tolerance)
        if len(ia) == 0:
            raise DataError(
                f"{self.root / 'rgb.txt'}: none of {len(rgb_ts)} colour frames has a depth frame in depth.txt "
                f"within {cfg.association_tolerance} s (expected matching timestamps)"
            )
        if len(ia) < len(rgb_ts):
            n = len(rgb_ts)
            log.info("%s: %d of %d colour frames have no depth frame and are skipped", self.root, n - len(ia), n)
        self.timestamps = rgb_ts[ia]
        self.rgb_files = [self.root / rgb_files[i] for i in ia]
        self.depth_files = [self.root / depth_files[j] for j in ib]
        self._camera = CAMERAS[cfg.camera or detect_camera(self.root)]
        gt_file = find_ground_truth(self.root, cfg.gt_path, "groundtruth.txt")
        self.gt_poses = None
        if gt_file is None:
            log.warning("no ground truth: %s not found; the sequence runs without it", self.root / "groundtruth.txt")
        else:
            gt_ts, gt = read_tum_trajectory(gt_file)
            self.gt_poses = interpolate_poses(gt_ts, gt, self.timestamps, cfg.gt_tolerance)

    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return len(self.timestamps)

    def raw_timestamp(self, raw_index: int) -> float:
        return float(self.timestamps[raw_index])

    def load(self, raw_index: int) -> Frame:
        rgb, depth = read_rgbd(self.rgb_files[raw_index], self.depth_files[raw_index], self.cfg.depth_scale,
                               self._camera)
        gt = None
        if self.gt_poses is not None and np.isfinite(self.gt_poses[raw_index]).all():
            gt = self.gt_poses[raw_index].copy()
        return Frame(raw_index, float(self.timestamps[raw_index]), rgb, depth, self._camera, gt)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("tum", TUMDataset, TUMConfig)]
