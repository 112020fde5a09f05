"""Extrapolating a G-ICP alignment along a slide (after Besl and McKay's accelerated ICP, 1992).

Each G-ICP iteration updates the pose by the Gauss-Newton step of the correspondences found at
it. Where the view pins the pose only weakly along a surface, the updates keep their direction
and shrink slowly, and the pose slides a little an iteration for tens of iterations
(docs/results.md, "A sliding alignment extrapolated"). When an update keeps the last one's
direction and has not grown much, the rest of the slide is estimated as a geometric series of
updates shrinking at their last ratio r (r / (1 - r) more of the update; r at most 1), at most
`factor` times the update and at most MAX_JUMP of the correspondence distance; the next
iteration starts there, and its update, from the correspondences found there, corrects it.
Anderson acceleration, tried first, extrapolated far past the updates when the correspondences
changed between iterations (the same section).

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
#: Nor one longer than this x the last: a slide's updates vary by about a tenth from one to the
#: next, and one that grows by more is no series converging (a weak direction would only drift).
MAX_GROWTH = 1.25
#: An extrapolation moves the pose at most this x the correspondence distance (chart metres), so
#: that the points stay within reach of their matches.
MAX_JUMP = 0.5


class SlideExtrapolation:
    """Extrapolation of one alignment from `start` (4x4 camera-to-world): `next_pose` is called
    once per accepted update. factor: the most the extrapolation adds, times the update;
    max_corr: the alignment's correspondence distance (metres), which bounds it by MAX_JUMP x."""

    def __init__(self, start: np.ndarray, factor: float, max_corr: float):
        self.R0, self.t0 = start[:3, :3].copy(), start[:3, 3].copy()
        self.factor = factor
        self.max_jump = MAX_JUMP * max_corr
        self.last: np.ndarray | None = None  # the last non-zero update, in the chart

    def _chart(self, T: np.ndarray) -> np.ndarray:
        return np.concatenate([so3_log(self.R0.T @ T[:3, :3]) * LEVER_M, self.R0.T @ (T[:3, 3] - self.t0)])

    def _pose(self, x: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R0 @ so3_exp(x[:3] / LEVER_M)
        T[:3, 3] = self.t0 + self.R0 @ x[3:]
        return T

    def next_pose(self, linearised: np.ndarray, updated: np.ndarray) -> np.ndarray:
        """Where the next iteration starts, given the pose this iteration linearised at and its
        update's result `updated` (both 4x4 camera-to-world): `updated`, or moved on along the
        update."""
        x = self._chart(updated)
        step = x - self._chart(linearised)
        n = float(np.linalg.norm(step))
        last = self.last
        if n > 0.0:
            self.last = step
        if last is None or not n > 0.0:
            return updated
        n_last = float(np.linalg.norm(last))
        # a turn, or an update that grew (no series to sum; a weak direction would only drift faster)
        if not (float(step @ last) >= MIN_COSINE * n * n_last and n <= MAX_GROWTH * n_last):
            return updated
        # after a jump the last update is the one before it, so r is low: the estimate is cautious
        r = min(n / n_last, 1.0)
        scale = self.factor if r * (1.0 + self.factor) >= self.factor else r / (1.0 - r)
        return self._pose(x + step * min(scale, self.max_jump / n))
