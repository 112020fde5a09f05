"""Training-view samplers (`sampler=random|covisible|recent`), and what their settings change."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.run.build import build_run
from slamkit_plugins.mappers.gaussian_splatting.sampler.keyframe_samplers import (
    CovisibleSampler,
    CovisibleSamplerConfig,
    RandomSampler,
    RecentSampler,
)


def look(yaw_deg: float, x: float = 0.0, z: float = 0.0) -> np.ndarray:
    a = math.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    T[0, 3], T[2, 3] = x, z
    return T


def draws(sampler, poses: dict, n: int = 300) -> set:
    """What `sampler` draws among `poses` (id -> pose, in arrival order: the last is the newest)."""
    rng = np.random.default_rng(0)
    return {sampler.sample(list(poses), poses, rng) for _ in range(n)}


def test_random_recent_and_covisible_choices():
    rng = np.random.default_rng(0)
    ids = [3, 4, 5, 6, 7]
    poses = {k: np.eye(4) for k in ids}
    counts = np.bincount([RandomSampler().sample(ids, poses, rng) for _ in range(2000)], minlength=8)[3:]
    assert counts.min() > 300 and counts.max() < 500  # uniform: 400 each
    assert RecentSampler().sample(ids, poses, rng) == 7
    poses = {0: look(180), 1: look(5, 0.1), 2: look(170), 3: look(-5), 4: look(90), 5: look(0)}
    sampler = CovisibleSampler()
    scores = sampler.scores(look(0), [poses[k] for k in range(6)])
    assert scores[5] == pytest.approx(1.0) and scores[0] == 0 and scores[2] == 0
    assert draws(sampler, poses) == {1, 3, 5}  # the three looking the newest's way, each drawn
    with pytest.raises(ValueError):
        RandomSampler().sample([], {}, rng)


def test_newest_share_is_the_share_of_draws_on_the_newest_keyframe():
    from slamkit_plugins.mappers.gaussian_splatting.sampler.keyframe_samplers import RandomSamplerConfig

    rng = np.random.default_rng(0)
    ids = list(range(10))
    draws_ = [RandomSampler(RandomSamplerConfig(newest_share=0.5)).sample(ids, {}, rng) for _ in range(4000)]
    assert np.mean(np.array(draws_) == 9) == pytest.approx(0.5 + 0.5 / 10, abs=0.03)
    with pytest.raises(ConfigError, match="mapper.sampler.newest_share"):
        RandomSamplerConfig(newest_share=1.5)


def test_top_k_is_how_many_of_the_most_covisible_are_drawn_from():
    poses = {0: look(3), 1: look(-20), 2: look(40), 3: look(180), 4: look(0)}  # 4: the newest
    assert draws(CovisibleSampler(CovisibleSamplerConfig(top_k=1)), poses) == {4}
    assert draws(CovisibleSampler(CovisibleSamplerConfig(top_k=2)), poses) == {4, 0}
    assert draws(CovisibleSampler(CovisibleSamplerConfig(top_k=4)), poses) == {4, 0, 1, 2}


def test_fov_deg_sets_the_frustums_compared():
    """A keyframe turned 40 degrees away shares part of a 90-degree view, none of a 20-degree one."""
    current, turned = look(0), [look(40)]
    assert CovisibleSampler(CovisibleSamplerConfig(fov_deg=90)).scores(current, turned)[0] > 0.2
    assert CovisibleSampler(CovisibleSamplerConfig(fov_deg=20)).scores(current, turned)[0] == 0


def test_max_depth_sets_how_far_the_probe_points_reach():
    """A keyframe 4 m ahead sees the current view's points only when they reach beyond it."""
    current, ahead = look(0), [look(0, z=4.0)]
    assert CovisibleSampler(CovisibleSamplerConfig(max_depth=3.0)).scores(current, ahead)[0] == 0
    assert CovisibleSampler(CovisibleSamplerConfig(max_depth=12.0)).scores(current, ahead)[0] > 0.1


@pytest.mark.parametrize("key, value", [("top_k", -1), ("top_k", 0), ("fov_deg", 180), ("max_depth", 0)])
def test_bad_settings_name_the_key(key, value):
    with pytest.raises(ConfigError, match=f"mapper.sampler.{key}: expected"):
        build_run(["mapper=gaussian_splatting", "mapper/sampler=covisible", f"mapper.sampler.{key}={value}"])
