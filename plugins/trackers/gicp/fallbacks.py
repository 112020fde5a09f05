"""The G-ICP tracker's fallbacks: when the alignment from the prediction is not trusted, which
other starts to try, and which result to keep (GICPConfig.fallback_to_previous, fallback_slide,
retry_unconverged, coarse_factor).

The first attempt starts from the prediction. When it does not converge (with
retry_unconverged), loses the frame or slides (ends more than fallback_slide *
max_correspondence_distance RMS from its start, e.g. after a sudden stop; up to twice that after
dropped frames, with the intervals the prediction spans; with stop_slid it stops there), it is
run again from the previous pose and, with coarse_factor > 1, coarse to fine from the
prediction (a motion the prediction missed by more than the correspondence distance); the
result matching more points is kept.
An attempt matching too few points (min_matched_fraction; after dropped frames
min_matched_ratio x the last frame's) is not trusted; when none is, the frame's points are
registered to the map without a first guess (relocalize_voxel; RANSAC from up to
relocalize_restarts seeds while none is trusted) and aligned from there. After a
gap longer than the prediction spans (max_prediction_intervals), where the input waits, every start
is tried, global registration included, whatever the first gave: the capped prediction is a
guess, and a first alignment from it can converge to a surface the map holds twice (drift) or
match a few points fewer than the right pose. There each attempt is also judged from the map's
side (`slamkit.geometry.surface`: of the image cells seeing the map, the fraction whose nearest
map centre lies on the frame's depth): one matching at least min_matched_fraction whose
agreement reaches min_surface_agreement is trusted below the ratio (the camera turned to surface
the map does not hold yet), and the trusted attempt kept is the one whose matched fraction x
agreement is the largest: a pose hugging a surface the map holds twice matches many points but
sees through the map elsewhere. The check is symmetric: map surface behind the frame's (new
foreground, a person walking in) lowers the right pose's agreement too. No fallback starts past
the frame's budget (frame_budget_ms, real time).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from slamkit_plugins.trackers.gicp.alignment import Aligner, matched_fraction, new_stats, point_moments, rms_travel
from slamkit_plugins.trackers.gicp.config import GICPConfig
from slamkit_plugins.trackers.gicp.target import Target

log = logging.getLogger(__name__)

#: The most the slide limit grows after dropped frames (x): after a long gap the prediction is
#: too poor to trust an alignment that ended farther from it (unbounded, a first alignment after
#: a long gap slid to a wrong pose and was kept; docs/results.md, "Tracking first").
MAX_SLIDE_GROWTH = 2.0
#: Stats summed over all attempts at a frame.
_EFFORT = ("nn_search_s", "solve_s", "iterations")


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
        self._warned = False  # that global registration is unavailable
        self._floor = cfg.min_matched_fraction  # the frame's least trusted matched fraction (solve)

    def solve(self, target: Target, src: np.ndarray, src_cov: np.ndarray, predicted: np.ndarray,
              previous: np.ndarray | None, stats: dict, intervals: float = 1.0, deadline: float | None = None,
              last_matched: float | None = None, beyond_prediction: bool = False,
              map_agreement: Callable[[np.ndarray], float | None] | None = None):
        """G-ICP of the source points (camera frame, metres) and covariances to the target from
        the predicted pose, with fallbacks; previous: the last tracked pose (None before the
        first); intervals: frame intervals the prediction spans (> 1 after dropped frames: the
        slide limit grows with it, as the prediction's error does, up to MAX_SLIDE_GROWTH x);
        deadline: time.perf_counter() seconds after which no fallback, nor an iteration of one,
        starts (the frame's budget in real time). An attempt matching less than
        min_matched_fraction of the points, or after dropped frames less than min_matched_ratio
        x `last_matched` (the last tracked frame's matched fraction), is not trusted (after a long
        gap, one converged to a wrong pose; docs/results.md, "Tracking first"): the fallbacks run,
        and when none is trusted the frame is lost. After a gap longer than the prediction spans
        (`beyond_prediction`: more than max_prediction_intervals) and without a deadline, every
        start is tried and, with `map_agreement` (a camera-to-world pose -> the map's surface
        agreement with the frame seen from it, None where too little map is in view) and
        min_surface_agreement set, each attempt is judged from the map's side too (`_judge`);
        else the trusted attempt matching most points is kept.
        Returns (pose, ok, squared NN distances of the kept attempt's last search)."""
        aligner = self.aligner
        slide_limit = self.cfg.fallback_slide * aligner.max_corr * min(max(1.0, intervals), MAX_SLIDE_GROWTH)
        moments = point_moments(src)
        # the first alignment runs to its end, bounded by stop_stalled and stop_slid, not by the
        # deadline: cut short under a busy CPU it ended unconverged and far off, and the map grew from it
        pose, ok, sq = aligner.align(target, src, src_cov, predicted, stats,
                                     max_travel=slide_limit if self.cfg.stop_slid else None, moments=moments)
        # relative to the last frame only after dropped frames: between two consecutive frames the
        # overlap with the map may fall for good (a camera leaving it, until the next keyframe)
        reference = (last_matched or 0.0) if intervals > 1 else 0.0
        self._floor = max(self.cfg.min_matched_fraction, self.cfg.min_matched_ratio * reference)
        slid = rms_travel(moments, predicted, pose) > slide_limit
        # only where the input waits (no deadline): a global registration outlasts many frame
        # intervals, and the frames dropped meanwhile would make the next frame another long gap
        relocalize = beyond_prediction and deadline is None
        # judged from the map's side only where every start is tried: one projection of the map per attempt
        agreement = map_agreement if relocalize and self.cfg.min_surface_agreement is not None else None
        ok, rank = self._judge(sq, pose, stats, agreement) if ok else (False, -1.0)
        if ok and (stats["converged"] or not self.retry_unconverged) and not slid and not relocalize:
            return pose, ok, sq
        # stopped on its way (stop_slid) its pose is anywhere along the slide: any trusted fallback is better
        best = (pose, ok, sq, -0.5 if ok and stats.get("slid") else rank)
        for name, start, coarse in self._starts(predicted, previous, target, src, deadline, stats, best[1],
                                                relocalize):
            if deadline is not None and time.perf_counter() > deadline:
                stats["out_of_time"] = True
                break
            retry = new_stats()
            if coarse:
                coarse_stats = new_stats()  # its own: the fine stage's count would overwrite it
                start, ok_coarse, _ = aligner.align(target, src, src_cov, start, coarse_stats,
                                                    aligner.max_corr * self.cfg.coarse_factor, deadline=deadline)
                _add_effort(stats, coarse_stats)
                if not ok_coarse:
                    continue
            pose2, ok2, sq2 = aligner.align(target, src, src_cov, start, retry, deadline=deadline)
            if coarse and ok2 and rms_travel(moments, start, pose2) > slide_limit:
                # the fine stage slid away from the coarse alignment: keep the coarse pose
                pose2, sq2 = start, aligner.match(target, src, start)
                retry["num_correspondences"] = int(np.isfinite(sq2).sum())
            ok2, rank = self._judge(sq2, pose2, retry, agreement) if ok2 else (False, -1.0)
            _add_effort(stats, retry)
            stats.setdefault("retried", []).append(name)
            if ok2 and rank > best[3]:
                stats.pop("lost_reason", None)
                stats.update({k: v for k, v in retry.items() if k not in _EFFORT and k != "covariance_s"})
                stats["fallback"] = name
                best = (pose2, ok2, sq2, rank)
            elif not best[1] and "lost_reason" in retry:
                stats["lost_reason"] = retry["lost_reason"]
        return best[:3]

    def _judge(self, sq: np.ndarray, pose: np.ndarray, stats: dict,
               agreement: Callable[[np.ndarray], float | None] | None) -> tuple[bool, float]:
        """Whether an alignment ending at `pose` is trusted, and its rank among the trusted ones
        (-1 when it is not). Trusted: it matched at least the frame's floor (`solve`) of the points
        within the correspondence distance at its last search; or, judged from the map's side
        (`agreement` given; its value kept in stats["surface_agreement"]), at least
        min_matched_fraction of them with the map seen from `pose` on the frame's depth in at
        least min_surface_agreement of the cells. Rank: its matched points; judged from the map's
        side, its matched fraction x surface agreement (the frame on the map and the map on the
        frame). Not trusted: stats["lost_reason"] says why."""
        cfg = self.cfg
        fraction = matched_fraction(sq)
        surface = None
        if agreement is not None:
            surface = stats["surface_agreement"] = agreement(pose)
        rank = float(stats.get("num_correspondences", 0)) if agreement is None else fraction * (surface or 0.0)
        if fraction >= self._floor:
            return True, rank
        if surface is not None and fraction >= cfg.min_matched_fraction and surface >= cfg.min_surface_agreement:
            return True, rank  # the map in view lies on the frame's depth: what did not match is new surface
        reason = (f"matched fraction {fraction:.2f} < {self._floor:.2f} (tracker.min_matched_fraction, "
                  "tracker.min_matched_ratio x the last frame's)")
        if agreement is not None and fraction >= cfg.min_matched_fraction:
            reason += (f", surface agreement {'none' if surface is None else f'{surface:.2f}'} < "
                       f"{cfg.min_surface_agreement:.2f} (tracker.min_surface_agreement)")
        stats["lost_reason"] = reason
        return False, -1.0

    def _starts(self, predicted: np.ndarray, previous: np.ndarray | None, target: Target, src: np.ndarray,
                deadline: float | None, stats: dict, trusted: bool, relocalize: bool = False):
        """(name, start pose, coarse first?) of the attempts after the first one; the last, when
        none so far is trusted (`trusted`: the first; then `stats["fallback"]`) or `relocalize`, is
        G-ICP from a global registration to the map (FPFH + RANSAC, without a first guess): after
        a long gap the camera may have turned tens of degrees (TUM fr1/rpy: 50-60 over 20
        frames), beyond any local start. Generated lazily: each start sees the ones before."""
        previous = self._previous_start(predicted, previous)
        if previous is not None:
            yield "previous pose", previous, False
        if self.cfg.coarse_factor > 1:
            yield "coarse to fine", predicted, True
        if self.cfg.relocalize_voxel <= 0:
            return
        source = None  # the frame's FeatureCloud (points, normals, FPFH): made once for every seed
        for seed in range(self.cfg.relocalize_restarts):
            # the first draw when nothing is trusted or after a long gap; another only while nothing is
            untrusted = not trusted and "fallback" not in stats
            out_of_time = deadline is not None and time.perf_counter() > deadline
            if not (untrusted or (relocalize and seed == 0)) or out_of_time:
                return
            start, source = self._relocalize(target, src, source, seed, stats)
            if start is None:
                return
            yield "global registration", start, False

    def _relocalize(self, target: Target, src: np.ndarray, source, seed: int, stats: dict) -> tuple:
        """The frame's pose by global registration of its points to the target's means, RANSAC
        drawing from `seed` (None without open3d, said once), and the points' FeatureCloud
        (`source` when given) for the next draw."""
        from slamkit.errors import SlamkitError
        from slamkit.geometry.registration import FeatureCloud, register

        voxel = self.cfg.relocalize_voxel
        try:
            source = FeatureCloud(src, voxel) if source is None else source
            found = register(source, target.features(voxel), seed=seed)
        except SlamkitError as exc:  # open3d is the optional extra `mesh`
            if not self._warned:
                log.warning("tracker.relocalize_voxel: no global registration (%s)", exc)
                self._warned = True
            return None, source
        stats["relocalized_fitness"], stats["relocalized_seed"] = found.fitness, seed
        return found.pose, source

    def _previous_start(self, predicted: np.ndarray, previous: np.ndarray | None) -> np.ndarray | None:
        """The previous pose, when the motion model moved the start away from it and
        `fallback_to_previous` is on; else None."""
        if not (self.cfg.fallback_to_previous and previous is not None):
            return None
        return None if np.array_equal(previous, predicted) else previous.copy()
