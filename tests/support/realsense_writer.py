"""RealSense recordings of the real TUM frames, made with no camera
(`slamkit_plugins.datasets.realsense.writer`: pyrealsense2's software device and recorder, the
.db3 that SDK 2.59 records): each colour image with the depth image TUM associates with it, both
at the colour's TUM timestamp, depth in TUM's 16-bit units (1/5000 m)."""

from __future__ import annotations

from pathlib import Path

from slamkit_plugins.datasets.realsense.writer import write_recording
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset

#: TUM's 16-bit depth: 5000 units per metre, so the device's depth scale is 1 / 5000 metres per unit.
TUM_UNITS_PER_METRE = 5000.0


def write_tum_recording(tum: Path, path: Path, n: int, fps: int = 30) -> Path:
    """A RealSense .db3 recording at `path` of the first `n` frames of the TUM folder `tum`."""
    return write_recording(TUMDataset(TUMConfig(path=str(tum), max_frames=n)), path, TUM_UNITS_PER_METRE, fps)
