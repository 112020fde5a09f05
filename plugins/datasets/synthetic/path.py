"""The synthetic sequence's camera path: a hand-held camera at 30 fps.

A smooth position (sums of sines, about 0.2-0.4 m/s) inside a free zone in the middle of the
room that keeps it >= 0.5 m from every surface, a heading that pans slowly around the room (up
to ~25 deg/s) while looking slightly down at the furniture, and small smooth roll / pitch / yaw
jitter. `seed` draws the path (start heading, pan direction, phases, frequencies). Poses are
camera-to-world 4x4 in the scene's world frame (metres, z up) with OpenCV camera axes (x right,
y down, z forward).

Paths that come back (`loop_path`, for loop closure, issue 46), each over the whole sequence
with the same hand-held jitter and downward look:

- `room_loop`: once around an ellipse (0.6 x 0.45 m) looking outwards, so the view pans once
  around the room, then on by 40 degrees: the last frames see the first frames' walls again.
- `figure_eight`: 1.1 times a figure eight (a 2:1 Lissajous curve), looking half-way towards
  where it goes: back at the start with the start's heading, and the crossing in the middle
  passed in two directions.
- `return`: the hand-held wander for three quarters of the sequence, then a smooth return to the
  first pose (position and rotation interpolated): a long path, then the start seen again.
- `revisit_rotated`: once around the ellipse looking outwards, then back round the other way on
  an ellipse half the size, turned 25 degrees further: each wall seen again from another place,
  in another direction and in the opposite order.

By default a path that comes back is at full speed from its first frame; `ramp_s` (seconds)
makes it start from rest and speed up evenly (and slow to rest at its end), as a camera picked
up rather than one already moving when the recording begins.
"""

from __future__ import annotations

import numpy as np

from slamkit.geometry.transforms import so3_exp, so3_log

#: Frames per second of the sequence (timestamps are raw_index / FPS).
FPS = 30.0

#: The free zone the camera centre stays in (|x| <= 0.7, |y| <= 0.55, z in [1.2, 1.7]); it is
#: >= 0.5 m from every surface (checked by the tests with `scene_clearance`).
PATH_BOUNDS = (np.array([-0.70, -0.55, 1.20]), np.array([0.70, 0.55, 1.70]))


#: The paths `loop_path` draws, besides the default `handheld` (`handheld_path`).
LOOP_PATHS = ("room_loop", "figure_eight", "return", "revisit_rotated")
#: The paths' ellipse (metres, semi-axes along x and y) around the free zone's centre height.
_ELLIPSE = (0.6, 0.45)
_CENTRE_Z = 1.45


class _Terms:
    """The seeded smooth terms of a path: s(amplitude, rad/s, k) = a sin(w f_k t + phase_k)."""

    def __init__(self, seed: int, t: np.ndarray):
        rng = np.random.default_rng([seed, 0x5EED])
        self.ph = rng.uniform(0, 2 * np.pi, 16)
        self.fm = rng.uniform(0.85, 1.15, 16)
        self.heading0 = rng.uniform(0, 2 * np.pi)
        self.pan = rng.choice([-1.0, 1.0])
        self.t = t

    def __call__(self, a: float, w: float, k: int) -> np.ndarray:
        return a * np.sin(w * self.fm[k] * self.t + self.ph[k])

    def jitter(self) -> np.ndarray:
        """(N,3) radians: small smooth rotations about the camera axes, a hand's tremor."""
        deg = np.pi / 180
        return np.stack([self(1.5 * deg, 2.1, 8) + self(0.6 * deg, 5.3, 9),
                         self(1.5 * deg, 1.7, 10) + self(0.6 * deg, 4.7, 11),
                         self(2.5 * deg, 1.3, 12) + self(0.8 * deg, 3.9, 13)], axis=1)


def _poses(pos: np.ndarray, heading: np.ndarray, pitch: np.ndarray, jitter: np.ndarray) -> np.ndarray:
    """(N,4,4) camera-to-world poses at `pos` (N,3 metres) looking along `heading` (N, radians
    from +x about +z) and `pitch` (N, radians, negative down), turned by `jitter` (N,3 radians
    about the camera's own axes)."""
    fwd = np.stack([np.cos(pitch) * np.cos(heading), np.cos(pitch) * np.sin(heading), np.sin(pitch)], 1)
    right = np.cross(fwd, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    look = np.stack([right, down, fwd], axis=2)  # columns: the camera's x, y, z in the world
    poses = np.zeros((len(pos), 4, 4))
    poses[:, :3, :3] = look @ np.stack([so3_exp(j) for j in jitter])
    poses[:, :3, 3] = pos
    poses[:, 3, 3] = 1.0
    return poses


def handheld_path(num_frames: int, seed: int = 0, speed: float = 1.0, fps: float = FPS) -> np.ndarray:
    """(num_frames, 4, 4) camera-to-world poses of a smooth hand-held-like path."""
    return _handheld(np.arange(num_frames) / fps * speed, seed)


def _handheld(t: np.ndarray, seed: int) -> np.ndarray:
    """The hand-held wander's poses at times `t` (seconds, scaled by the speed)."""
    s = _Terms(seed, t)
    # Position: |x| <= 0.45 + 0.25, |y| <= 0.35 + 0.2, z in 1.45 +- (0.16 + 0.08).
    pos = np.stack([s(0.45, 0.35, 0) + s(0.25, 0.83, 1), s(0.35, 0.41, 2) + s(0.20, 0.97, 3),
                    _CENTRE_Z + s(0.16, 0.50, 4) + s(0.08, 1.30, 5)], axis=1)
    # Heading pans around the room (0.2 rad/s plus a slow swing), looking ~20 deg down.
    heading = s.heading0 + s.pan * 0.20 * t + s(0.35, 0.45, 6)
    pitch = -0.35 + s(0.12, 0.60, 7)
    return _poses(pos, heading, pitch, s.jitter())


def _ellipse(theta: np.ndarray, scale: float | np.ndarray, s: _Terms) -> np.ndarray:
    """(N,3) metres: points of the path's ellipse, scaled (a factor, or one per point), at
    angles `theta`, bobbing in height."""
    a, b = _ELLIPSE
    return np.stack([scale * a * np.cos(theta), scale * b * np.sin(theta),
                     _CENTRE_Z + 0.06 * np.sin(3 * theta) + s(0.03, 1.3, 5)], axis=1)


def from_rest(num_frames: int, ramp_s: float, fps: float = FPS) -> np.ndarray:
    """(num_frames,) progress 0..1 along a path that starts and ends at rest: its speed rises
    evenly over the first `ramp_s` seconds, stays constant, and falls evenly over the last
    (a trapezoid of speed; symmetric: progress(i) + progress(n-1-i) = 1). 0 seconds: constant
    speed. The two ramps must fit in the path (at most half of it each)."""
    v = np.linspace(0.0, 1.0, num_frames)
    if ramp_s <= 0:
        return v
    r = ramp_s * fps / max(num_frames - 1, 1)
    if r > 0.5:
        raise ValueError(f"a ramp of {ramp_s} s is longer than half the path's {num_frames} frames at {fps} frames/s")
    top = 1.0 / (1.0 - r)  # the constant part's speed, so that progress ends at 1
    return np.where(v < r, top * v * v / (2 * r),
                    np.where(v > 1 - r, 1 - top * (1 - v) ** 2 / (2 * r), top * (v - r / 2)))


def loop_path(kind: str, num_frames: int, seed: int = 0, fps: float = FPS, ramp_s: float = 0.0) -> np.ndarray:
    """(num_frames, 4, 4) camera-to-world poses of the path `kind` (one of LOOP_PATHS, see the
    module docstring), spread over the whole sequence: more frames, a slower camera. With
    `ramp_s` > 0 (seconds) the camera starts and ends at rest (`from_rest`); with 0 it is moving
    at full speed from the first frame to the last."""
    if kind not in LOOP_PATHS:
        raise ValueError(f"synthetic path: expected one of {', '.join(LOOP_PATHS)}, got {kind!r}")
    # progress along the path
    u = from_rest(num_frames, ramp_s, fps) if ramp_s > 0 else np.linspace(0.0, 1.0, num_frames)
    s = _Terms(seed, np.arange(num_frames) / fps)
    pitch = -0.35 + s(0.08, 0.60, 7)
    if kind == "room_loop":
        theta = s.heading0 + s.pan * (2 * np.pi + np.radians(40.0)) * u
        return _poses(_ellipse(theta, 1.0, s), theta, pitch, s.jitter())
    if kind == "figure_eight":
        phi = 2 * np.pi * 1.1 * u
        a, b = _ELLIPSE
        pos = np.stack([a * np.sin(phi), b * np.sin(2 * phi), _CENTRE_Z + s(0.05, 0.5, 4)], axis=1)
        # half-way between the tangent and the start's heading: looking where it goes turns at
        # up to 80 deg/s in the lobes; the tangent turns by 0 over a period, so this comes back too
        heading = s.heading0 + 0.5 * np.unwrap(np.arctan2(2 * b * np.cos(2 * phi), a * np.cos(phi)))
        return _poses(pos, heading, pitch, s.jitter())
    if kind == "return":
        wander = int(round(0.75 * num_frames))
        # with a ramp the wander starts from rest (the first half of a trapezoid twice its length);
        # the way back (a smoothstep) ends at rest either way
        t = np.arange(wander) / fps if ramp_s <= 0 else \
            from_rest(2 * wander, ramp_s, fps)[:wander] * (2 * wander - 1) / fps
        out = _handheld(t, seed)
        v = np.linspace(0.0, 1.0, num_frames)
        w = v[: num_frames - wander + 1] / v[num_frames - wander]  # 0..1 over the way back
        w = w * w * (3 - 2 * w)  # smoothstep: at rest on arriving at the start pose
        first, last = out[0], out[-1]
        back = np.zeros((len(w), 4, 4))
        turn = so3_log(last[:3, :3].T @ first[:3, :3])
        back[:, :3, :3] = last[:3, :3] @ np.stack([so3_exp(x * turn) for x in w])
        back[:, :3, 3] = (1 - w)[:, None] * last[:3, 3] + w[:, None] * first[:3, 3]
        back[:, 3, 3] = 1.0
        return np.concatenate([out, back[1:]])
    # revisit_rotated: round the ellipse outwards, then back (the angle eases in and out of the
    # turn), shrinking to half and turning 25 degrees further while it turns round
    theta = s.heading0 + s.pan * 2 * np.pi * np.sin(np.pi * u)
    g = np.clip((u - 0.4) / 0.2, 0.0, 1.0)
    g = g * g * (3 - 2 * g)
    return _poses(_ellipse(theta, 1.0 - 0.5 * g, s), theta + s.pan * np.radians(25.0) * g, pitch, s.jitter())
