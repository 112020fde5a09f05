"""The G-ICP tracker's fallbacks: when the alignment from the prediction is not trusted, which
other starts to try, and which result to keep (GICPConfig.fallback_to_previous, fallback_slide,
retry_unconverged, coarse_factor).

The first attempt starts from the prediction. When it does not converge (with
retry_unconverged), loses the frame or slides (ends more than fallback_slide *
max_correspondence_distance RMS from its start, e.g. after a sudden stop; up to twice that after
dropped frames, with the intervals the prediction spans), it is run again from the previous
pose and, with coarse_factor > 1, coarse to fine from the prediction (a motion the prediction
missed by more than the correspondence distance); the result matching more points is kept.
"""

from __future__ import annotations

import numpy as np

from slamkit.geometry.transforms import invert_pose
from slamkit_plugins.trackers.gicp.alignment import Aligner, new_stats
from slamkit_plugins.trackers.gicp.config import GICPConfig
from slamkit_plugins.trackers.gicp.target import Target

#: The most the slide limit grows after dropped frames (x): after a long gap the prediction is
#: too poor to trust an alignment that ended farther from it (unbounded, a first alignment after
#: a long gap slid to a wrong pose and was kept; docs/results.md, "Tracking first").
MAX_SLIDE_GROWTH = 2.0
#: Stats summed over all attempts at a frame.
_EFFORT = ("nn_search_s", "solve_s", "iterations")


def _moved(src: np.ndarray, start: np.ndarray, end: np.ndarray) -> float:
    """RMS displacement in metres of the source points between two poses."""
    D = invert_pose(start) @ end
    return float(np.sqrt(np.mean(np.sum((src @ (D[:3, :3] - np.eye(3)).T + D[:3, 3]) ** 2, axis=1))))


def _add_effort(stats: dict, retry: dict) -> None:
    """Add a retry's effort (seconds, iterations) to the frame's."""
    for key in _EFFORT:
        stats[key] += retry[key]


class FallbackPolicy:
    """G-ICP from the prediction with the fallbacks above, on top of an `Aligner`."""

    def __init__(self, cfg: GICPConfig, aligner: Aligner):
        self.cfg = cfg
        self.aligner = aligner
        self.retry_unconverged = cfg.retry_unconverged is not False  # null (unresolved): as sequential

    def solve(self, target: Target, src: np.ndarray, src_cov: np.ndarray, predicted: np.ndarray,
              previous: np.ndarray | None, stats: dict, intervals: float = 1.0):
        """G-ICP of the source points (camera frame, metres) and covariances to the target from
        the predicted pose, with fallbacks; previous: the last tracked pose (None before the
        first); intervals: frame intervals the prediction spans (> 1 after dropped frames: the
        slide limit grows with it, as the prediction's error does, up to MAX_SLIDE_GROWTH x).
        Returns (pose, ok, squared NN distances of the kept attempt's last search)."""
        aligner = self.aligner
        pose, ok, sq = aligner.align(target, src, src_cov, predicted, stats)
        slide_limit = self.cfg.fallback_slide * aligner.max_corr * min(max(1.0, intervals), MAX_SLIDE_GROWTH)
        if ok and (stats["converged"] or not self.retry_unconverged) and _moved(src, predicted, pose) <= slide_limit:
            return pose, ok, sq
        best = (pose, ok, sq, stats.get("num_correspondences", 0) if ok else -1)
        for name, start, coarse in self._starts(predicted, previous):
            retry = new_stats()
            if coarse:
                start, ok_coarse, _ = aligner.align(target, src, src_cov, start, retry,
                                                    aligner.max_corr * self.cfg.coarse_factor)
                if not ok_coarse:
                    _add_effort(stats, retry)
                    continue
            pose2, ok2, sq2 = aligner.align(target, src, src_cov, start, retry)
            if coarse and ok2 and _moved(src, start, pose2) > slide_limit:
                # the fine stage slid away from the coarse alignment: keep the coarse pose
                pose2, sq2 = start, aligner.match(target, src, start)
                retry["num_correspondences"] = int(np.isfinite(sq2).sum())
            _add_effort(stats, retry)
            stats.setdefault("retried", []).append(name)
            if ok2 and retry["num_correspondences"] > best[3]:
                stats.pop("lost_reason", None)
                stats.update({k: v for k, v in retry.items() if k not in _EFFORT and k != "covariance_s"})
                stats["fallback"] = name
                best = (pose2, ok2, sq2, retry["num_correspondences"])
        return best[:3]

    def _starts(self, predicted: np.ndarray, previous: np.ndarray | None):
        """(name, start pose, coarse first?) of the attempts after the first one failed."""
        previous = self._previous_start(predicted, previous)
        if previous is not None:
            yield "previous pose", previous, False
        if self.cfg.coarse_factor > 1:
            yield "coarse to fine", predicted, True

    def _previous_start(self, predicted: np.ndarray, previous: np.ndarray | None) -> np.ndarray | None:
        """The previous pose, when the motion model moved the start away from it and
        `fallback_to_previous` is on; else None."""
        if not (self.cfg.fallback_to_previous and previous is not None):
            return None
        return None if np.array_equal(previous, predicted) else previous.copy()
