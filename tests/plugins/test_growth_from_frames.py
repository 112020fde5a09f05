"""Issue 41 point 1: a keyframe's Gaussians are the map's business. Made by the growth from the
frame at its tracked pose (`slamkit.map.growth.frame_gaussians`), they are G-ICP's handed-over
source Gaussians (the same points, covariances, colours and depths), so that any tracker feeds the
3DGS mapper; and a tracker that hands none over grows the map all the same."""

from __future__ import annotations

import numpy as np

from slamkit.map.growth import frame_gaussians
from slamkit.run.build import build_run


def test_the_growth_makes_a_keyframes_gaussians_as_gicp_hands_them_over(tum_path):
    dataset, slam, _ = build_run(["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=2",
                                  "mapper=gaussian_splatting"])
    frame = dataset[0]
    slam.initialize(frame.gt_pose)
    handed = slam.tracker.track(frame).gaussians
    made = frame_gaussians(frame, frame.gt_pose, slam.growth, np.empty((0, 3)))
    assert len(made) == len(handed) > 1000
    np.testing.assert_array_equal(made.means, handed.means)
    np.testing.assert_array_equal(made.colors, handed.colors)
    np.testing.assert_array_equal(made.depths, handed.depths)
    np.testing.assert_array_equal(made.trackable, handed.trackable)
    np.testing.assert_allclose(made.shape_covariances, handed.shape_covariances, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(made.covariances, handed.covariances, rtol=1e-6, atol=1e-9)
    assert np.isinf(made.sq_dist_to_map).all()  # nothing in the map yet


def test_a_tracker_that_hands_no_gaussians_over_grows_the_map_near_the_first_keyframes(tum_path):
    dataset, slam, _ = build_run(["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=12",
                                  "tracker=kiss_icp", "mapper=gaussian_splatting", "iterations_per_frame=1"])
    slam.initialize(dataset[0].gt_pose)
    steps = [slam.process(dataset[i]) for i in range(len(dataset))]
    assert all(s.tracking.gaussians is None for s in steps)  # KISS-ICP keeps its own voxel map
    gm = slam.gaussian_map
    assert slam.num_keyframes >= 2 and len(gm) > 1000
    assert set(gm.keyframe_id.tolist()) == set(range(slam.num_keyframes))
    # the first keyframe's Gaussians lie on the first frame's surface, placed at its pose
    first = frame_gaussians(dataset[0], steps[0].tracking.pose, slam.growth, np.empty((0, 3)))
    rows = (gm.keyframe_id == 0).numpy()
    entered = gm.entry_means.detach().numpy()[rows]
    assert np.isin(entered.view([("", entered.dtype)] * 3), first.means.view([("", first.means.dtype)] * 3)).all()
