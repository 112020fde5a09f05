"""Feeding the selected viewer (`viewer=NAME`) from the run loop, so that it can never stop a run.

`ViewerFeed` turns each processed frame into a `slamkit.roles.ViewerFrame` (with the trajectory so
far, moved with the loop closure's corrections, and its loops) and calls the viewer. The first
exception a viewer raises is logged as a warning naming it, and the viewer gets no more frames
(only `close`, so that a recording keeps what it has).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from slamkit.map.gaussian_map import GaussianMap
from slamkit.roles import Mapper, Viewer, ViewerFrame
from slamkit.run.loop_closing import Correction
from slamkit.types import Camera, Frame, KeyframeKind

log = logging.getLogger(__name__)


class ViewerFeed:
    """Calls `viewer` (plugin `name`) with every processed frame; see the module docstring."""

    def __init__(self, viewer: Viewer, name: str, gaussian_map: GaussianMap, mapper: Mapper):
        self.viewer, self.name = viewer, name
        self.gaussian_map, self.mapper = gaussian_map, mapper
        self.failed = False
        self.last_view: ViewerFrame | None = None
        self._centres: list[np.ndarray] = []
        self._keyframe_positions: list[int] = []  # indices into _centres of the keyframes shown
        self._gt_centres: list[np.ndarray] = []

    def start(self, camera: Camera, out_dir: Path) -> None:
        """Open the viewer with the dataset's camera and the run folder."""
        self._call("start", camera, out_dir)

    def show(self, frame: Frame, pose: np.ndarray, keyframe: KeyframeKind, lost: bool,
             loops: np.ndarray | None = None) -> None:
        """Hand one processed frame (its estimated camera-to-world `pose`) to the viewer, with the
        loop closure's accepted loops as (L,2,3) camera-centre pairs (world metres)."""
        if keyframe:
            self._keyframe_positions.append(len(self._centres))
        self._centres.append(np.asarray(pose, dtype=np.float64)[:3, 3].copy())
        if frame.gt_pose is not None and np.all(np.isfinite(frame.gt_pose)):
            self._gt_centres.append(np.asarray(frame.gt_pose, dtype=np.float64)[:3, 3].copy())
        if self.failed:
            return
        self.last_view = ViewerFrame(
            frame=frame,
            pose=np.asarray(pose, dtype=np.float64),
            keyframe=keyframe,
            lost=lost,
            trajectory=np.array(self._centres).reshape(-1, 3),
            gt_trajectory=np.array(self._gt_centres).reshape(-1, 3),
            gaussian_map=self.gaussian_map,
            mapper=self.mapper,
            keyframes=np.array([self._centres[i] for i in self._keyframe_positions]).reshape(-1, 3),
            loops=np.zeros((0, 2, 3)) if loops is None else np.asarray(loops, dtype=np.float64).reshape(-1, 2, 3),
        )
        self._call("show", self.last_view)

    def follow(self, correction: Correction) -> None:
        """The trajectory shown so far follows a loop closure's correction."""
        if not self._centres:
            return
        poses = np.tile(np.eye(4), (len(self._centres), 1, 1))
        poses[:, :3, 3] = self._centres
        self._centres = list(correction.follow(poses, self._keyframe_positions)[:, :3, 3])

    def close(self) -> None:
        """Close the viewer (also after it failed: a recording keeps what it has)."""
        self._call("close", self.last_view, after_failure=True)

    def _call(self, method: str, *args, after_failure: bool = False) -> None:
        if self.failed and not after_failure:
            return
        try:
            getattr(self.viewer, method)(*args)
        except Exception as exc:
            log.debug("viewer %r failed in %s()", self.name, method, exc_info=True)
            first_line = f"{type(exc).__name__}: {exc}".splitlines()[0]
            more = "" if self.failed else "; it is switched off, the run goes on"
            log.warning("viewer %r failed in %s(): %s%s", self.name, method, first_line, more)
            self.failed = True
