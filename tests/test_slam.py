"""The SLAM loop with the G-ICP tracker and the `none` mapper (tracking only)."""

from __future__ import annotations

import numpy as np

from slamkit.config import apply_hints
from slamkit.gaussian_map import GaussianMap
from slamkit.map_growth import MapGrowthConfig
from slamkit.registry import default_registry
from slamkit.slam import SLAM


def _run(keep_untrackable: bool, frames: int = 30):
    registry = default_registry()
    dataset = registry.create("dataset", "synthetic", registry.get("dataset", "synthetic").config(num_frames=frames))
    configs = {role: registry.get(role, name).config() for role, name in
               [("tracker", "gicp"), ("keyframe", "overlap"), ("mapper", "none")]}
    configs["mapper"].keep_untrackable = keep_untrackable
    growth = MapGrowthConfig()
    for cfg in [*configs.values(), growth]:
        apply_hints(cfg, dataset.hints)
    names = {"tracker": "gicp", "keyframe": "overlap", "mapper": "none"}
    slam = SLAM(*(registry.create(role, names[role], configs[role]) for role in ("tracker", "keyframe", "mapper")),
                GaussianMap(), growth)
    slam.initialize(dataset[0].gt_pose)
    poses = [slam.step(dataset[i]).tracking.pose for i in range(len(dataset))]
    return np.array(poses), slam


def test_tracking_only_map_keeps_only_trackable_gaussians_without_changing_tracking():
    lean_poses, lean = _run(keep_untrackable=False)
    full_poses, full = _run(keep_untrackable=True)
    assert lean.num_keyframes == full.num_keyframes >= 2
    assert bool(lean.gaussian_map.trackable.all())
    assert len(lean.gaussian_map) < 0.8 * len(full.gaussian_map)
    np.testing.assert_allclose(lean_poses, full_poses, atol=1e-9)  # the target is the same


def test_mapping_threads_leave_one_cpu_to_the_tracker_in_realtime_mode(monkeypatch):
    import torch

    from slamkit.config import Mode, RunConfig
    from slamkit.pipeline import mapping_threads

    monkeypatch.setattr(torch, "get_num_threads", lambda: 4)
    assert mapping_threads(RunConfig(mode=Mode.sequential)) == 4
    assert mapping_threads(RunConfig(mode=Mode.realtime)) == 3
    assert mapping_threads(RunConfig(mode=Mode.realtime, mapping_threads=2)) == 2
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert mapping_threads(RunConfig(mode=Mode.realtime)) == 1


def test_tracking_threads_default_to_one_in_realtime_mode(monkeypatch):
    from slamkit.config import Mode, RunConfig
    from slamkit.pipeline import tracking_threads

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert tracking_threads(RunConfig(mode=Mode.sequential)) == 3
    assert tracking_threads(RunConfig(mode=Mode.realtime)) == 1
