"""The synthetic sequence's camera path: a hand-held camera at 30 fps.

A smooth position (sums of sines, about 0.2-0.4 m/s) inside a free zone in the middle of the
room that keeps it >= 0.5 m from every surface, a heading that pans slowly around the room (up
to ~25 deg/s) while looking slightly down at the furniture, and small smooth roll / pitch / yaw
jitter. `seed` draws the path (start heading, pan direction, phases, frequencies). Poses are
camera-to-world 4x4 in the scene's world frame (metres, z up) with OpenCV camera axes (x right,
y down, z forward).
"""

from __future__ import annotations

import numpy as np

from slamkit.geometry.transforms import so3_exp

#: Frames per second of the sequence (timestamps are raw_index / FPS).
FPS = 30.0

#: The free zone the camera centre stays in (|x| <= 0.7, |y| <= 0.55, z in [1.2, 1.7]); it is
#: >= 0.5 m from every surface (checked by the tests with `scene_clearance`).
PATH_BOUNDS = (np.array([-0.70, -0.55, 1.20]), np.array([0.70, 0.55, 1.70]))


def camera_path(num_frames: int, seed: int = 0, speed: float = 1.0, fps: float = FPS) -> np.ndarray:
    """(num_frames, 4, 4) camera-to-world poses of a smooth hand-held-like path."""
    rng = np.random.default_rng([seed, 0x5EED])
    ph = rng.uniform(0, 2 * np.pi, 16)
    fm = rng.uniform(0.85, 1.15, 16)
    heading0 = rng.uniform(0, 2 * np.pi)
    pan = rng.choice([-1.0, 1.0])
    t = np.arange(num_frames) / fps * speed

    def s(a, w, k):
        return a * np.sin(w * fm[k] * t + ph[k])

    # Position: |x| <= 0.45 + 0.25, |y| <= 0.35 + 0.2, z in 1.45 +- (0.16 + 0.08).
    pos = np.stack(
        [
            s(0.45, 0.35, 0) + s(0.25, 0.83, 1),
            s(0.35, 0.41, 2) + s(0.20, 0.97, 3),
            1.45 + s(0.16, 0.50, 4) + s(0.08, 1.30, 5),
        ],
        axis=1,
    )
    # Heading pans around the room (0.2 rad/s plus a slow swing), looking ~20 deg down.
    heading = heading0 + pan * 0.20 * t + s(0.35, 0.45, 6)
    pitch = -0.35 + s(0.12, 0.60, 7)
    fwd = np.stack([np.cos(pitch) * np.cos(heading), np.cos(pitch) * np.sin(heading), np.sin(pitch)], 1)
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    # Hand-held jitter: small smooth rotations about the camera axes (radians).
    deg = np.pi / 180
    jit = np.stack(
        [
            s(1.5 * deg, 2.1, 8) + s(0.6 * deg, 5.3, 9),
            s(1.5 * deg, 1.7, 10) + s(0.6 * deg, 4.7, 11),
            s(2.5 * deg, 1.3, 12) + s(0.8 * deg, 3.9, 13),
        ],
        axis=1,
    )
    poses = np.zeros((num_frames, 4, 4))
    for i in range(num_frames):
        R_look = np.stack([right[i], down[i], fwd[i]], axis=1)
        poses[i, :3, :3] = R_look @ so3_exp(jit[i])
        poses[i, :3, 3] = pos[i]
        poses[i, 3, 3] = 1.0
    return poses
