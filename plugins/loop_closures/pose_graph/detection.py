"""Loop candidates: earlier keyframes that look at the same place, by estimated pose and by
appearance, with no learned weights.

Place: a keyframe's place is the point it looks at, its camera centre plus its median depth
along its optical axis (world frame, from the current pose estimates). A candidate's place lies
within a radius that grows with the camera path between the two keyframes (odometry drifts with
the path), and its optical axis within an angle of the keyframe's. Appearance: a zero-mean,
unit-norm 32x24 grey image (area-averaged), compared by cosine similarity; candidates are ranked
by it, the most similar first.
"""

from __future__ import annotations

import numpy as np

#: The appearance descriptor's grey image size (columns, rows).
DESCRIPTOR_SIZE = (32, 24)


def appearance_descriptor(image: np.ndarray) -> np.ndarray:
    """(32*24,) float32, zero mean and unit norm (zeros for a flat image): the (h,w,3) colour
    image in grey, averaged over 32x24 equal areas."""
    grey = np.asarray(image, dtype=np.float64).mean(axis=2)
    cols, rows = DESCRIPTOR_SIZE
    # an image smaller than the descriptor: each pixel repeated, so that every area holds one
    grey = np.repeat(np.repeat(grey, -(-rows // grey.shape[0]), axis=0), -(-cols // grey.shape[1]), axis=1)
    r = np.linspace(0, grey.shape[0], rows + 1).astype(int)[:-1]
    c = np.linspace(0, grey.shape[1], cols + 1).astype(int)[:-1]
    sums = np.add.reduceat(np.add.reduceat(grey, r, axis=0), c, axis=1)
    counts = np.diff(np.append(r, grey.shape[0]))[:, None] * np.diff(np.append(c, grey.shape[1]))[None, :]
    d = (sums / counts).ravel()
    d -= d.mean()
    norm = np.linalg.norm(d)
    return (d / norm if norm > 0 else d).astype(np.float32)


def view_point(pose: np.ndarray, median_depth: float) -> np.ndarray:
    """(3,) metres, world: the point `median_depth` metres along the optical axis (+z) of the
    camera-to-world `pose`."""
    return pose[:3, 3] + median_depth * pose[:3, 2]


def place_candidates(poses: np.ndarray, depths: np.ndarray, path: np.ndarray, query: int, eligible: np.ndarray,
                     radius_m: float, radius_per_path: float, max_angle_deg: float) -> np.ndarray:
    """Indices (into the keyframe arrays) of the `eligible` keyframes whose place is near keyframe
    `query`'s: poses (K,4,4) camera-to-world, depths (K,) median depths in metres, path (K,)
    metres of camera path from the first keyframe; the radius is radius_m + radius_per_path *
    (path[query] - path[candidate])."""
    eligible = np.asarray(eligible, dtype=np.int64)
    if len(eligible) == 0:
        return eligible
    places = poses[eligible, :3, 3] + depths[eligible, None] * poses[eligible, :3, 2]
    here = view_point(poses[query], float(depths[query]))
    radius = radius_m + radius_per_path * (path[query] - path[eligible])
    cos_angle = poses[eligible, :3, 2] @ poses[query, :3, 2]
    near = (np.linalg.norm(places - here, axis=1) <= radius) & (cos_angle >= np.cos(np.radians(max_angle_deg)))
    return eligible[near]
