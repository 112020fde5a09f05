"""Keyframe samplers: which keyframe the mapper trains on next (paper Table 8a).

- `random` (the paper's choice, its best in Table 8a): uniform over all keyframes so far, so the
  whole map keeps being trained and no view's local minimum dominates; optionally a share of the
  draws on the newest keyframe (`newest_share`).
- `covisible`: uniform among the `top_k` keyframes whose view overlaps
  the current one most. Overlap is the fraction of a fixed set of points inside the current
  camera's viewing frustum (a grid over a `fov_deg` cone at depths up to `max_depth` metres) that
  also lie inside the keyframe's frustum, so it needs the keyframes' poses.
- `recent`: always the newest keyframe (the paper's worst).

A sampler is a part of the 3DGS mapper, selected with ``mapper/sampler=covisible mapper.sampler.top_k=3``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import KeyframeSampler, PluginConfig, RunContext, require


@dataclass
class RandomSamplerConfig(PluginConfig):
    """Uniform draws over all keyframes."""

    #: the share of draws that take the newest keyframe, the rest uniform over all (0: uniform, the paper's)
    newest_share: float = 0.0

    def validate(self) -> None:
        require(0 <= self.newest_share <= 1, "mapper.sampler.newest_share", "in [0, 1]", self.newest_share)


class RandomSampler(KeyframeSampler):
    """Uniform over all keyframes (a `newest_share` of the draws: the newest)."""

    def __init__(self, cfg: RandomSamplerConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg or RandomSamplerConfig()

    def sample(self, keyframe_ids, keyframe_poses, rng) -> int:
        _check(keyframe_ids)
        if self.cfg.newest_share and rng.random() < self.cfg.newest_share:
            return keyframe_ids[-1]
        return keyframe_ids[int(rng.integers(len(keyframe_ids)))]


@dataclass
class RecentSamplerConfig(PluginConfig):
    """No options."""


class RecentSampler(KeyframeSampler):
    """The newest keyframe (the last of `keyframe_ids`, which lists them in arrival order)."""

    def __init__(self, cfg: RecentSamplerConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg or RecentSamplerConfig()

    def sample(self, keyframe_ids, keyframe_poses, rng) -> int:
        _check(keyframe_ids)
        return keyframe_ids[-1]


@dataclass
class CovisibleSamplerConfig(PluginConfig):
    """Draws among the keyframes that see most of what the newest one sees."""

    #: choose uniformly among this many most covisible keyframes
    top_k: int = 3
    #: degrees; the full field of view (both axes) assumed for the frustums
    fov_deg: float = 60.0
    #: metres; the depth of the probe points (a 7x7 grid at 4 depths from max_depth/4 to max_depth)
    max_depth: float = 3.0

    def validate(self) -> None:
        require(self.top_k >= 1, "mapper.sampler.top_k", "an integer >= 1", self.top_k)
        require(0 < self.fov_deg < 180, "mapper.sampler.fov_deg", "in (0, 180) degrees", self.fov_deg)
        require(self.max_depth > 0, "mapper.sampler.max_depth", "> 0 metres", self.max_depth)


class CovisibleSampler(KeyframeSampler):
    """Uniform among the `top_k` keyframes with the largest frustum overlap with the newest
    keyframe's."""

    def __init__(self, cfg: CovisibleSamplerConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg or CovisibleSamplerConfig()
        t = math.tan(math.radians(self.cfg.fov_deg) / 2)
        g = np.linspace(-t, t, 7)
        xs, ys = np.meshgrid(g, g)
        rays = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], axis=1)
        depths = np.linspace(self.cfg.max_depth / 4, self.cfg.max_depth, 4)
        self._probe = (rays[None] * depths[:, None, None]).reshape(-1, 3)  # camera frame
        self._tan = t

    def scores(self, current_pose: np.ndarray, poses: list[np.ndarray]) -> np.ndarray:
        """Overlap in [0, 1] of each pose's frustum with the current one's."""
        world = self._probe @ current_pose[:3, :3].T + current_pose[:3, 3]
        out = np.empty(len(poses))
        for i, pose in enumerate(poses):
            local = (world - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - t)
            z = local[:, 2]
            limit = self._tan * z + 1e-9
            inside = (z > 1e-6) & (np.abs(local[:, 0]) <= limit) & (np.abs(local[:, 1]) <= limit)
            out[i] = inside.mean()
        return out

    def sample(self, keyframe_ids, keyframe_poses: Mapping[int, np.ndarray], rng) -> int:
        _check(keyframe_ids)
        current = np.asarray(keyframe_poses[keyframe_ids[-1]])  # the newest keyframe's view
        s = self.scores(current, [np.asarray(keyframe_poses[k]) for k in keyframe_ids])
        k = min(self.cfg.top_k, len(keyframe_ids))
        best = np.argsort(-s, kind="stable")[:k]
        return keyframe_ids[int(best[int(rng.integers(k))])]


def _check(keyframe_ids) -> None:
    if len(keyframe_ids) == 0:
        raise ValueError("no keyframe to sample from")


@hookimpl
def slamkit_plugins():
    return [
        PluginSpec("random", RandomSampler, RandomSamplerConfig),
        PluginSpec("covisible", CovisibleSampler, CovisibleSamplerConfig),
        PluginSpec("recent", RecentSampler, RecentSamplerConfig),
    ]
