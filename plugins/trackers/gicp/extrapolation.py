"""Extrapolating the G-ICP alignment along a slide (after Besl and McKay's accelerated ICP, 1992).

Each G-ICP iteration steps the pose by the Gauss-Newton update of the correspondences found at
it. Where the view pins the pose weakly along a surface the updates keep their direction and
shrink slowly: the pose slides a millimetre or two an iteration for tens of iterations (TUM
fr1/rpy frame 52: 32 iterations, successive updates at cosines 0.97-1.00). When an update keeps
the last one's direction, the rest of the slide is estimated as a geometric series of updates
shrinking at their last ratio r (r / (1 - r) more of the update, r at most `MAX_RATIO`) and taken
at once, at most `factor` times the update; the next update, from the new correspondences,
corrects it. (Anderson acceleration over two or three iterations was tried first: with the
correspondences changing between iterations its least squares extrapolated ten times past the
updates and some alignments ran out their iterations; docs/results.md.)

Updates are compared in a chart at the alignment's start T0: x = (log(R0^T R) * LEVER_M,
R0^T (t - t0)), so that rotation and translation are both metres.
"""

from __future__ import annotations

import numpy as np

from slamkit.geometry.transforms import so3_exp, so3_log

#: metres: the lever arm turning the chart's rotation (radians) into a displacement, about the
#: depth of the points an RGB-D frame aligns (so a unit of either moves them alike).
LEVER_M = 1.0
#: An update whose cosine with the last one is below this is not extrapolated.
MIN_COSINE = 0.9
#: The shrink ratio the series assumes is at most this (a constant slide: the factor's cap).
MAX_RATIO = 0.95


class SlideExtrapolation:
    """Extrapolation of one alignment from `start` (4x4 camera-to-world): `next_pose` is called
    once per accepted update; factor: the most the extrapolation adds, times the update."""

    def __init__(self, start: np.ndarray, factor: float):
        self.R0, self.t0 = start[:3, :3].copy(), start[:3, 3].copy()
        self.factor = factor
        self.last: np.ndarray | None = None  # the last update, in the chart

    def _chart(self, T: np.ndarray) -> np.ndarray:
        return np.concatenate([so3_log(self.R0.T @ T[:3, :3]) * LEVER_M, self.R0.T @ (T[:3, 3] - self.t0)])

    def _pose(self, x: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R0 @ so3_exp(x[:3] / LEVER_M)
        T[:3, 3] = self.t0 + self.R0 @ x[3:]
        return T

    def next_pose(self, T: np.ndarray, updated: np.ndarray) -> np.ndarray:
        """The pose to iterate from next, given this iteration's pose `T` and its update's
        result `updated` (both 4x4 camera-to-world): `updated`, or moved on along the update."""
        x = self._chart(updated)
        step = x - self._chart(T)
        last, self.last = self.last, step
        n = float(np.linalg.norm(step))
        if last is None or n == 0.0:
            return updated
        n_last = float(np.linalg.norm(last))
        if float(step @ last) < MIN_COSINE * n * n_last:
            return updated
        r = min(n / n_last, MAX_RATIO)
        return self._pose(x + step * min(r / (1.0 - r), self.factor))
