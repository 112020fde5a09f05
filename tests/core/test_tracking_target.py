"""The tracker's target from the map (`GaussianMap.tracking_target`): the trackable Gaussians with
the geometry they entered the map with, through training and pruning, or their current
(optimised) geometry. The tracking this gives beside the mapper, on real data:
tests/e2e/test_tracking_under_mapping.py."""

from __future__ import annotations

import numpy as np
import torch

from slamkit.map.gaussian_map import GaussianMap, GaussianRows

from support.mapping_scenes import plane_scene


def test_the_map_keeps_the_entry_geometry_through_training_and_pruning():
    """entry_* hold the values appended, follow the row operations, and are what
    tracking_target() returns, while geometry="optimised" returns the current values."""
    means, quats, scales, colors, _ = plane_scene(n=10)
    trackable = np.arange(10) % 3 != 0
    gm = GaussianMap()
    gm.append(GaussianRows.from_shapes(means, quats, scales, colors, 0.5, trackable, 0))
    with torch.no_grad():  # what an optimiser does
        gm.means += 0.01
        gm.quats += 0.1
        gm.log_scales += 0.5
    keep = torch.ones(10, dtype=torch.bool)
    keep[[1, 2, 3]] = False
    gm.keep(keep)
    kept = trackable & keep.numpy()
    np.testing.assert_array_equal(gm.tracking_target().means, means[kept])
    target_var = np.sort(torch.linalg.eigvalsh(torch.as_tensor(gm.tracking_target().covariances, dtype=torch.float64))
                         .numpy(), axis=1)
    np.testing.assert_allclose(target_var, np.sort(scales[kept] ** 2, axis=1), rtol=1e-4)
    np.testing.assert_allclose(gm.tracking_target(geometry="optimised").means, means[kept] + 0.01, rtol=1e-6)
    assert len(gm.tracking_target(min_opacity=0.6).means) == 0
