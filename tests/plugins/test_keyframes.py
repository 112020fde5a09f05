"""Keyframe policies: the correspondence ratio and scripted decision sequences."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.config import RunContext
from slamkit.errors import ConfigError
from slamkit.roles import KeyframeDecision
from slamkit.tuning import DatasetTuning
from slamkit.types import Camera, Frame, FrameGaussians, KeyframeKind, TrackingResult
from slamkit_plugins.keyframes.every_n import EveryNKeyframeConfig, EveryNKeyframePolicy
from slamkit_plugins.keyframes.every_n import slamkit_plugins as every_n_hook
from slamkit_plugins.keyframes.overlap import (
    OverlapKeyframeConfig,
    OverlapKeyframePolicy,
    correspondence_ratio,
)
from slamkit_plugins.keyframes.overlap import slamkit_plugins as overlap_hook

N, T, M = KeyframeKind.NONE, KeyframeKind.TRACKING, KeyframeKind.MAPPING_ONLY
CAMERA = Camera(4, 4, 1.0, 1.0, 1.5, 1.5)


def frame(i: int) -> Frame:
    return Frame(index=i, timestamp=i / 30, rgb=np.zeros((4, 4, 3), np.uint8), depth=np.zeros((4, 4), np.float32),
                 camera=CAMERA)


def result_with_ratio(ratio: float, n: int = 100, threshold: float = 1e-3) -> TrackingResult:
    """A result whose trackable points overlap the map in the given fraction (plus 20
    non-trackable points that always overlap and must not count)."""
    k = int(round(ratio * n))
    sq = np.concatenate([np.full(k, 0.1 * threshold), np.full(n - k, np.inf), np.zeros(20)])
    trackable = np.concatenate([np.ones(n, bool), np.zeros(20, bool)])
    m = n + 20
    g = FrameGaussians(means=np.zeros((m, 3)), covariances=np.zeros((m, 3, 3)), colors=np.zeros((m, 3)),
                       depths=np.ones(m), trackable=trackable, sq_dist_to_map=sq)
    return TrackingResult(pose=np.eye(4), gaussians=g)


def test_correspondence_ratio_counts_trackable_points_below_threshold():
    sq = np.array([1e-4, 5e-4, 9.99e-4, 1e-3, 2e-3, np.inf, 0.0, 0.0])
    trackable = np.array([1, 1, 1, 1, 1, 1, 0, 0], bool)
    g = FrameGaussians(means=np.zeros((8, 3)), covariances=np.zeros((8, 3, 3)), colors=np.zeros((8, 3)),
                       depths=np.ones(8), trackable=trackable, sq_dist_to_map=sq)
    r = TrackingResult(pose=np.eye(4), gaussians=g)
    assert correspondence_ratio(r, 1e-3) == pytest.approx(3 / 6)  # strictly below the threshold
    assert correspondence_ratio(r, 5e-4) == pytest.approx(1 / 6)
    assert correspondence_ratio(r, 1.0) == pytest.approx(5 / 6)  # inf never counts
    g.trackable[:] = False
    assert correspondence_ratio(r, 1e-3) == 0.0
    # Without Gaussians the tracker's own ratio (or None) is used.
    assert correspondence_ratio(TrackingResult(pose=np.eye(4), correspondence_ratio=0.4), 1e-3) == 0.4
    assert correspondence_ratio(TrackingResult(pose=np.eye(4)), 1e-3) is None


def test_overlap_policy_scripted_sequence():
    policy = OverlapKeyframePolicy(OverlapKeyframeConfig(overlap_threshold=1e-3, keyframe_threshold=0.8,
                                                         mapping_every=3))
    ratios = [0.0, 0.95, 0.9, 0.85, 0.82, 0.79, 0.9, 0.9, 0.9, 0.9, 0.5, 0.99]
    expected = [T, N, N, M, N, T, N, N, M, N, T, N]
    got = []
    for i, r in enumerate(ratios):
        res = result_with_ratio(r)
        decision = policy.decide(frame(i), res)
        got.append(decision.kind)
        # the ratio is the decision's, not written into the tracker's result
        assert decision.correspondence_ratio == pytest.approx(r) and res.correspondence_ratio is None
    assert got == expected


def test_overlap_policy_first_frame_always_tracking_and_mapping_disabled():
    policy = OverlapKeyframePolicy(OverlapKeyframeConfig(overlap_threshold=1e-3, keyframe_threshold=0.5,
                                                         mapping_every=0))
    got = [policy.decide(frame(i), result_with_ratio(1.0 if i else 0.99)).kind for i in range(25)]
    assert got == [T] + [N] * 24


def test_overlap_policy_counts_lost_frames_by_index():
    """The pipeline skips decide() for lost frames; mapping-only spacing follows frame indices."""
    policy = OverlapKeyframePolicy(OverlapKeyframeConfig(overlap_threshold=1e-3, keyframe_threshold=0.5,
                                                         mapping_every=4))
    assert policy.decide(frame(0), result_with_ratio(0.0)).kind is T
    assert policy.decide(frame(1), result_with_ratio(0.9)).kind is N
    # frames 2..4 lost
    assert policy.decide(frame(5), result_with_ratio(0.9)).kind is M
    assert policy.decide(frame(6), result_with_ratio(0.9)).kind is N
    assert policy.decide(frame(9), result_with_ratio(0.9)).kind is M


def test_overlap_policy_max_interval_forces_tracking_keyframe():
    policy = OverlapKeyframePolicy(OverlapKeyframeConfig(overlap_threshold=1e-3, keyframe_threshold=0.5,
                                                         mapping_every=10, max_interval=30))
    got = [policy.decide(frame(i), result_with_ratio(0.99)).kind for i in range(61)]
    assert [i for i, k in enumerate(got) if k is T] == [0, 30, 60]
    assert [i for i, k in enumerate(got) if k is M] == [10, 20, 40, 50]


def test_overlap_policy_reads_its_null_thresholds_from_the_dataset_tuning():
    cfg = OverlapKeyframeConfig()
    assert cfg.overlap_threshold is None and cfg.keyframe_threshold is None and cfg.mapping_every == 10
    policy = OverlapKeyframePolicy(cfg.resolve(RunContext()))
    assert (policy.overlap_threshold, policy.keyframe_threshold) == (1e-3, 0.81)  # a hand-held camera (TUM)
    replica = RunContext(tuning=DatasetTuning(keyframe_overlap=5e-4, keyframe_threshold=0.7))
    policy = OverlapKeyframePolicy(cfg.resolve(replica))
    assert (policy.overlap_threshold, policy.keyframe_threshold) == (5e-4, 0.7)
    policy = OverlapKeyframePolicy(OverlapKeyframeConfig(keyframe_threshold=0.5).resolve(replica))
    assert (policy.overlap_threshold, policy.keyframe_threshold) == (5e-4, 0.5)
    with pytest.raises(ConfigError, match="keyframe.keyframe_threshold"):
        OverlapKeyframeConfig(keyframe_threshold=1.5)
    with pytest.raises(ConfigError, match="keyframe.mapping_every"):
        OverlapKeyframeConfig(mapping_every=-1)


def test_overlap_policy_ratio_uses_the_threshold():
    """A point at squared distance 2e-4 overlaps under 5e-4 (Replica) but not under 1e-4."""
    def result():
        g = FrameGaussians(means=np.zeros((10, 3)), covariances=np.zeros((10, 3, 3)), colors=np.zeros((10, 3)),
                           depths=np.ones(10), trackable=np.ones(10, bool), sq_dist_to_map=np.full(10, 2e-4))
        return TrackingResult(pose=np.eye(4), gaussians=g)

    loose = OverlapKeyframePolicy(OverlapKeyframeConfig(overlap_threshold=5e-4, keyframe_threshold=0.7))
    tight = OverlapKeyframePolicy(OverlapKeyframeConfig(overlap_threshold=1e-4, keyframe_threshold=0.7))
    for p in (loose, tight):
        p.decide(frame(0), result())
    r1, r2 = result(), result()
    assert loose.decide(frame(1), r1) == KeyframeDecision(N, 1.0)
    assert tight.decide(frame(1), r2) == KeyframeDecision(T, 0.0)


def test_every_n_scripted_sequence():
    policy = EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=5, mapping_every=2))
    got = [policy.decide(frame(i), result_with_ratio(0.5)).kind for i in range(12)]
    assert got == [T, N, M, N, M, T, N, M, N, M, T, N]
    only = EveryNKeyframePolicy(EveryNKeyframeConfig())
    got = [only.decide(frame(i), TrackingResult(pose=np.eye(4))).kind for i in range(61)]
    assert [i for i, k in enumerate(got) if k] == [0, 30, 60]
    assert all(k in (T, N) for k in got)


def test_every_n_with_lost_frames_and_validation():
    policy = EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=3))
    assert policy.decide(frame(0), TrackingResult(pose=np.eye(4))).kind is T
    # frames 1..3 lost: the next frame asked is overdue and becomes the keyframe
    assert policy.decide(frame(4), TrackingResult(pose=np.eye(4))).kind is T
    assert policy.decide(frame(5), TrackingResult(pose=np.eye(4))).kind is N
    with pytest.raises(ConfigError, match="keyframe.tracking_every"):
        EveryNKeyframeConfig(tracking_every=0)


def test_hooks_register_policies():
    (o,) = overlap_hook()
    (e,) = every_n_hook()
    assert (o.name, o.cls, o.config) == ("overlap", OverlapKeyframePolicy, OverlapKeyframeConfig)
    assert (e.name, e.cls, e.config) == ("every_n", EveryNKeyframePolicy, EveryNKeyframeConfig)
