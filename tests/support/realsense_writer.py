"""RealSense recordings of the real TUM frames, made with no camera, by the name's suffix: a .db3
(`slamkit_plugins.datasets.realsense.writer`: pyrealsense2's software device and recorder, what
SDK 2.59 records) or a ROS1 .bag (`slamkit_plugins.datasets.realsense.bag`: the SDK's older
layout, written with rosbags): each colour image with the depth image TUM associates with it,
both at the colour's TUM timestamp, depth in TUM's 16-bit units (1/5000 m)."""

from __future__ import annotations

from pathlib import Path

from slamkit_plugins.datasets.realsense.bag import write_bag_recording
from slamkit_plugins.datasets.realsense.writer import write_recording
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset

#: TUM's 16-bit depth: 5000 units per metre, so the device's depth scale is 1 / 5000 metres per unit.
TUM_UNITS_PER_METRE = 5000.0


def write_tum_recording(tum: Path, path: Path, n: int, fps: int = 30) -> Path:
    """A RealSense recording at `path` (.db3 or .bag) of the first `n` frames of the TUM folder `tum`."""
    write = write_bag_recording if Path(path).suffix == ".bag" else write_recording
    return write(TUMDataset(TUMConfig(path=str(tum), max_frames=n)), path, TUM_UNITS_PER_METRE, fps)


class TumRecordings:
    """The recordings of the first `n` frames of the TUM folder `tum` in the folder `root`, by
    suffix (`recordings(".bag")`), each written once, when first asked for."""

    def __init__(self, tum: Path, root: Path, n: int):
        self.tum, self.root, self.n = tum, root, n
        self._made: dict[str, Path] = {}

    def __call__(self, suffix: str = ".db3") -> Path:
        if suffix not in self._made:
            self._made[suffix] = write_tum_recording(self.tum, self.root / f"fr1{suffix}", self.n)
        return self._made[suffix]
