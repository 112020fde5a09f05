"""The G-ICP kernels' threads come from slamkit's persistent pool: a real sequence tracks to the
same poses, bit for bit, on one thread and on two."""

from __future__ import annotations

import numpy as np

from slamkit.run.build import build_run


def _poses(tum_path, threads: int, frames: int = 20) -> np.ndarray:
    dataset, slam, _ = build_run(["dataset=tum", f"dataset.path={tum_path}", f"dataset.max_frames={frames}",
                                  "tracker=gicp", "tracker.kernels=compiled", f"tracker.num_threads={threads}",
                                  "keyframe=overlap", "mapper=none"])
    slam.initialize(dataset[0].gt_pose)
    return np.array([slam.process(dataset[i]).tracking.pose for i in range(len(dataset))])


def test_a_real_sequence_tracks_the_same_on_one_thread_and_on_two(tum_path):
    one, two = _poses(tum_path, 1), _poses(tum_path, 2)
    assert one.tobytes() == two.tobytes()
    assert np.linalg.norm(one[-1][:3, 3] - one[0][:3, 3]) > 0.01  # it moved: the frames were tracked
