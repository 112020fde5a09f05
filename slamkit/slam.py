"""The SLAM loop over one shared Gaussian map, free of I/O (see `slamkit.pipeline` for that)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from slamkit.gaussian_map import GaussianMap
from slamkit.map_growth import MapGrowthConfig, add_keyframe_gaussians
from slamkit.roles import KeyframePolicy, Mapper, Tracker
from slamkit.types import Frame, KeyframeKind, TrackingResult


@dataclass
class StepResult:
    """One frame's outcome. Times in seconds."""

    tracking: TrackingResult
    keyframe: KeyframeKind
    tracking_time_s: float
    mapping_time_s: float
    mapping_iterations: int


class SLAM:
    """GS-ICP SLAM: a tracker and a mapper sharing one GaussianMap (sequential mode).

    Each frame is tracked against the map; keyframes add their Gaussians to the map (a tracking
    keyframe also rebuilds the tracker's target from the map, which by then holds the mapper's
    optimised values); then the mapper runs a fixed number of iterations, so the run is
    deterministic.
    """

    def __init__(
        self,
        tracker: Tracker,
        keyframe_policy: KeyframePolicy,
        mapper: Mapper,
        gaussian_map: GaussianMap,
        map_growth: MapGrowthConfig,
        iterations_per_frame: int = 0,
    ):
        self.tracker = tracker
        self.keyframe_policy = keyframe_policy
        self.mapper = mapper
        self.gaussian_map = gaussian_map
        self.map_growth = map_growth
        self.iterations_per_frame = iterations_per_frame
        self.num_keyframes = 0
        mapper.bind(gaussian_map)

    def initialize(self, first_pose: np.ndarray) -> None:
        """Set the pose (camera-to-world) the trajectory starts from."""
        self.tracker.initialize(first_pose)

    def step(self, frame: Frame) -> StepResult:
        start = time.perf_counter()
        result = self.tracker.track(frame, self.gaussian_map)
        kind = KeyframeKind.NONE if result.lost else self.keyframe_policy.decide(frame, result)
        if kind:
            self.add_keyframe(frame, result, kind)
        tracked = time.perf_counter()
        iterations = self.mapper.optimize(self.iterations_per_frame)
        return StepResult(result, kind, tracked - start, time.perf_counter() - tracked, iterations)

    def add_keyframe(self, frame: Frame, result: TrackingResult, kind: KeyframeKind) -> None:
        rows = slice(len(self.gaussian_map), len(self.gaussian_map))
        if result.gaussians is not None:
            rows = add_keyframe_gaussians(self.gaussian_map, result.gaussians, self.num_keyframes, self.map_growth)
        if kind is KeyframeKind.TRACKING:
            self.tracker.update_target(self.gaussian_map)
        self.mapper.add_keyframe(frame, result, kind, rows)
        self.num_keyframes += 1
