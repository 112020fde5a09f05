"""The built-in synthetic RGB-D sequence: a furnished room rendered along a hand-held path.

Nothing is downloaded: the scene is analytic (a 6 x 5 x 3 m room seen from inside, with a sofa,
a table, a cabinet, a bookshelf, a floor lamp, a stool, balls, a rug, a door, a window, pictures,
a clock, a ceiling beam and lamp), rendered by vectorised numpy ray casting against boxes,
spheres and cylinders. Every surface has its own procedural texture (planks, tiles, checkers,
stripes, value noise, gradients) computed from the hit point, shaded by a fixed directional
light (Lambertian, so colours do not depend on the viewpoint). Depth is exact (the camera-frame
z of the hit, no holes) and ground truth is the rendering pose.

The camera moves like a hand-held camera at 30 fps: a smooth position (sums of sines, about
0.2-0.4 m/s) inside a free zone in the middle of the room that keeps it >= 0.5 m from every
surface, a heading that pans slowly around the room (up to ~25 deg/s) while looking slightly
down at the furniture, and small smooth roll / pitch / yaw jitter. `seed` draws the path
(start heading, pan direction, phases, frequencies); the scene itself never changes.

World frame: metres, z up, the floor at z = 0, the room spans x in [-3, 3], y in [-2.5, 2.5].
Poses are camera-to-world with OpenCV camera axes (x right, y down, z forward).

The sequence is generated once (a few seconds for the default 120 frames at 320x240) and
cached as one compressed .npz per parameter set (rgb uint8, depth uint16 at 0.2 mm) in
`cache_dir` (null = $SLAMKIT_CACHE/synthetic, else ~/.cache/slamkit/synthetic); later
constructions open the cache and decode frames on demand. Depth noise and dropout are applied
at load time (deterministic per seed and frame), so they share the noise-free cache.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from slamkit.errors import DataError
from slamkit.geometry.transforms import so3_exp
from slamkit.roles import Dataset, DatasetConfig, SensorProfile, require
from slamkit.types import Camera, Frame

log = logging.getLogger(__name__)

#: Bump when the scene, the path or the renderer changes: old cache files are then ignored.
GENERATOR_VERSION = 1
#: Frames per second of the sequence (timestamps are raw_index / FPS).
FPS = 30.0
#: Depth is cached as uint16 with this many units per metre (0.2 mm steps, up to 13.1 m; the
#: room's farthest point from the camera is < 8 m).
DEPTH_SCALE = 5000.0


@dataclass
class SyntheticConfig(DatasetConfig):
    """The generated sequence.

    num_frames: frames in the sequence (30 per second of motion). width, height: image size in
    pixels. fov_deg: horizontal field of view in degrees; the rendering camera has square
    pixels, fx = fy = (width / 2) / tan(fov_deg / 2) (64 deg gives fx ~ 256 at 320 wide) and
    the principal point at the image centre, cx = (width - 1) / 2, cy = (height - 1) / 2.
    seed: draws the camera path (the scene is fixed). speed: multiplies the camera's linear and
    angular speeds (the same path, traversed faster). depth_noise: metres of Gaussian depth
    noise at 1 m, growing with z^2 as a Kinect's does (0 = exact depth; the default 1.5 mm is
    a Kinect v1's, so that the default run is not a noiseless toy). depth_dropout:
    fraction of pixels whose depth is set to 0 (invalid) at random. cache_dir: folder of the
    cached sequences (null = $SLAMKIT_CACHE/synthetic, else ~/.cache/slamkit/synthetic).

    `path` is not used (the sequence is generated, not read); `fx`, `fy`, `cx`, `cy` override
    the intrinsics *reported* with each frame, as for every dataset, without changing what is
    rendered (e.g. to study calibration errors): to render another camera use `fov_deg`,
    `width` and `height`.
    """

    num_frames: int = 120
    width: int = 320
    height: int = 240
    fov_deg: float = 64.0
    seed: int = 0
    speed: float = 1.0
    depth_noise: float = 0.0015
    depth_dropout: float = 0.0
    cache_dir: str | None = None

    def validate(self) -> None:
        super().validate()
        require(self.num_frames >= 2, "dataset.num_frames", "an integer >= 2", self.num_frames)
        require(16 <= self.width <= 8192, "dataset.width", "an integer in [16, 8192] pixels", self.width)
        require(16 <= self.height <= 8192, "dataset.height", "an integer in [16, 8192] pixels", self.height)
        require(
            10.0 <= self.fov_deg <= 150.0,
            "dataset.fov_deg",
            "a horizontal field of view in [10, 150] degrees",
            self.fov_deg,
        )
        require(self.seed >= 0, "dataset.seed", "an integer >= 0", self.seed)
        require(0.0 < self.speed <= 10.0, "dataset.speed", "a factor in (0, 10]", self.speed)
        require(self.depth_noise >= 0.0, "dataset.depth_noise", ">= 0 metres", self.depth_noise)
        require(0.0 <= self.depth_dropout < 1.0, "dataset.depth_dropout", "a fraction in [0, 1)", self.depth_dropout)


# ------------------------------------------------------------------------------------------
# Procedural textures. Inputs: points (n, 3) float32 in metres; `fw` (n,) the footprint of a
# pixel in metres (textures are box-filtered over it, so fine patterns fade to their mean
# colour at a distance instead of aliasing). Outputs: (n,) weights in [0, 1] or (n, 3) colours.
# ------------------------------------------------------------------------------------------

_NOISE_N = 32  # value-noise lattice period (cells)
_NOISE_TABLE = np.random.default_rng(918273).random(_NOISE_N**3).astype(np.float32)


def _rot(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in degrees."""
    a, b, c = np.radians([yaw, pitch, roll])
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    return rz @ ry @ rx


# Fixed rotations decorrelate the octaves of the noise (and hide the lattice's axes).
_OCTAVE_ROT = [_rot(0, 0, 0), _rot(37, 21, 11), _rot(-53, 47, -29), _rot(71, -13, 59)]


_OCTAVE_ROT32 = [r.astype(np.float32) for r in _OCTAVE_ROT]


def _value_noise(qx: np.ndarray, qy: np.ndarray, qz: np.ndarray) -> np.ndarray:
    """Smooth value noise in [0, 1] at lattice coordinates (qx, qy, qz); period 32 cells."""
    m = _NOISE_N - 1
    idx, wts = [], []
    for q, stride in ((qx, _NOISE_N * _NOISE_N), (qy, _NOISE_N), (qz, 1)):
        f = np.floor(q)
        w = q - f
        wts.append(w * w * (np.float32(3.0) - np.float32(2.0) * w))
        i = f.astype(np.int32) & m
        idx.append((i * stride, ((i + 1) & m) * stride))
    (x0, x1), (y0, y1), (z0, z1) = idx
    wx, wy, wz = wts
    t = _NOISE_TABLE
    out = None
    for zz, sz in ((z0, None), (z1, wz)):
        a0, a1 = x0 + zz, x1 + zz
        c0 = np.take(t, a0 + y0)
        c0 += (np.take(t, a1 + y0) - c0) * wx
        c1 = np.take(t, a0 + y1)
        c1 += (np.take(t, a1 + y1) - c1) * wx
        c0 += (c1 - c0) * wy
        out = c0 if sz is None else out + (c0 - out) * sz
    return out


def _fbm(p: np.ndarray, scale: float | np.ndarray, octaves: int = 2, offset: float = 0.0) -> np.ndarray:
    """Fractal value noise in [0, 1] at points p (n, 3): `octaves` octaves, the first with
    features ~`scale` m (a 3-vector scale stretches the noise, e.g. wood grain)."""
    sc = np.broadcast_to(np.asarray(scale, np.float32), (3,))
    cols = [p[:, k] * np.float32(1.0 / sc[k]) for k in range(3)]
    total, amp, norm = None, 1.0, 0.0
    for o in range(octaves):
        M = _OCTAVE_ROT32[o % 4] * np.float32(2.0**o)
        off = np.float32(offset + 7.31 * o)
        q = [cols[0] * M[0, j] + cols[1] * M[1, j] + cols[2] * M[2, j] + off for j in range(3)]
        n = _value_noise(*q)
        total = n if total is None else total + np.float32(amp) * n
        norm += amp
        amp *= 0.5
    return total * np.float32(1.0 / norm)


def _pulse(u: np.ndarray, duty: float, w: np.ndarray) -> np.ndarray:
    """Box-filtered pulse train: 1 where frac(u) < duty, else 0, averaged over a window of
    width w (all in periods)."""
    w = np.maximum(w, 0.02)

    def integral(x):
        fl = np.floor(x)
        return fl * duty + np.minimum(x - fl, duty)

    return np.clip((integral(u + 0.5 * w) - integral(u - 0.5 * w)) / w, 0.0, 1.0)


def _stripes(x: np.ndarray, period: float, fw: np.ndarray, duty: float = 0.5) -> np.ndarray:
    return _pulse(x / period, duty, fw / period)


def _checker(p: np.ndarray, cell: float, fw: np.ndarray) -> np.ndarray:
    """3D checkerboard with cells of `cell` metres (0 / 1), box-filtered."""
    s = np.ones(len(p), np.float32)
    for k in range(3):
        s *= 2.0 * _pulse(p[:, k] / (2 * cell) + 0.123 * (k + 1), 0.5, fw / (2 * cell)) - 1.0
    return 0.5 - 0.5 * s


def _mix(c0, c1, t: np.ndarray) -> np.ndarray:
    c0, c1 = np.asarray(c0, np.float32), np.asarray(c1, np.float32)
    return c0 + (c1 - c0) * t[:, None]


def _hash01(i: np.ndarray, salt: int = 0) -> np.ndarray:
    """Pseudo-random value in [0, 1) per integer."""
    h = (i.astype(np.int64) * 0x2C1B3C6D + salt * 0x297A2D39) & 0xFFFFFFFF
    h ^= h >> 15
    h = (h * 0x297A2D39) & 0xFFFFFFFF
    h ^= h >> 12
    return (h & 0xFFFF).astype(np.float32) / 65536.0


# A material maps a hit to colours: f(h) -> (n, 3) float in [0, 1], with h a _Hit.


@dataclass
class _Hit:
    p: np.ndarray  # (n, 3) world points
    pl: np.ndarray  # (n, 3) points in the primitive's local frame
    nl: np.ndarray  # (n, 3) local normals
    face: np.ndarray  # (n,) int: box faces 2*axis + (normal > 0); cylinders 4 / 5 caps, 6 side
    fw: np.ndarray  # (n,) pixel footprint in metres


Material = Callable[[_Hit], np.ndarray]


def _mat_solid(c, noise_amp: float = 0.08, scale: float = 0.3) -> Material:
    def f(h):
        return np.asarray(c, np.float32) * (1 - noise_amp + 2 * noise_amp * _fbm(h.p, scale, 2))[:, None]

    return f


def _mat_checker(c0, c1, cell: float, noise_amp: float = 0.06) -> Material:
    def f(h):
        col = _mix(c0, c1, _checker(h.pl, cell, h.fw))
        return col * (1 - noise_amp + 2 * noise_amp * _fbm(h.p, 0.25, 1, 3.0))[:, None]

    return f


def _mat_noise(c0, c1, scale: float, octaves: int = 3, contrast: float = 1.6) -> Material:
    def f(h):
        n = np.clip(0.5 + contrast * (_fbm(h.pl, scale, octaves, 11.0) - 0.5), 0, 1)
        return _mix(c0, c1, n)

    return f


def _mat_wood(c0, c1, grain_axis: int = 0, ring: float = 0.035) -> Material:
    """Wood: noise-warped stripes across the grain plus fine streaks along it."""
    stretch = np.full(3, 0.02, np.float32)
    stretch[grain_axis] = 0.6

    def f(h):
        q = h.pl
        other = [k for k in range(3) if k != grain_axis]
        d = q[:, other[0]] + 0.6 * q[:, other[1]] + 0.08 * _fbm(q, 0.5, 2, 5.0)
        rings = _stripes(d, ring, h.fw, 0.35)
        streak = _fbm(q, stretch, 2, 17.0)
        return _mix(c0, c1, np.clip(0.55 * rings + 0.8 * (streak - 0.5) + 0.25, 0, 1))

    return f


def _mat_floor(h: _Hit) -> np.ndarray:
    """Wooden planks along x, 0.18 m wide, with staggered ends, seams and grain."""
    p = h.p
    plank = np.floor(p[:, 1] / 0.18)
    r = _hash01(plank, 1)
    end_u = p[:, 0] / 1.3 + r
    board = np.floor(end_u) * 97 + plank
    tint = _hash01(board, 2)
    grain = _fbm(p + tint[:, None] * 3.0, np.array([0.7, 0.012, 0.012], np.float32), 2, 2.0)
    base = _mix((0.50, 0.33, 0.19), (0.74, 0.54, 0.33), np.clip(0.3 + 0.5 * tint + 0.7 * (grain - 0.5), 0, 1))
    seam = np.maximum(_stripes(p[:, 1] - 0.005, 0.18, h.fw, 0.05), _stripes(end_u * 1.3 - 0.005, 1.3, h.fw, 0.01))
    return base * (1.0 - 0.6 * seam)[:, None]


def _mat_ceiling(h: _Hit) -> np.ndarray:
    """Acoustic ceiling tiles: 0.6 m squares, grey grid lines, faint speckle."""
    p = h.p
    lines = np.maximum(_stripes(p[:, 0] + 0.01, 0.6, h.fw, 0.035), _stripes(p[:, 1] + 0.01, 0.6, h.fw, 0.035))
    speckle = _fbm(p, 0.05, 2, 9.0)
    base = _mix((0.80, 0.80, 0.78), (0.95, 0.94, 0.90), speckle)
    return base * (1 - 0.45 * lines)[:, None]


def _mat_wall_west(h: _Hit) -> np.ndarray:
    """Blue plaster above a white wainscot with vertical boards, a dark dado rail at 0.9 m."""
    p = h.p
    upper = _mix((0.42, 0.55, 0.72), (0.62, 0.74, 0.86), _fbm(p, 0.6, 3, 1.0))
    boards = _mix((0.93, 0.92, 0.88), (0.70, 0.70, 0.68), _stripes(p[:, 1], 0.12, h.fw, 0.12))
    lower = (p[:, 2] < 0.9).astype(np.float32)
    col = upper * (1 - lower)[:, None] + boards * lower[:, None]
    rail = np.clip(1.0 - np.abs(p[:, 2] - 0.9) / 0.03, 0, 1)
    return col * (1 - 0.7 * rail)[:, None]


def _mat_wall_east(h: _Hit) -> np.ndarray:
    """Beige wallpaper with a diamond pattern."""
    p = h.p
    a = (p[:, 1] + p[:, 2]) * 0.7071
    b = (p[:, 1] - p[:, 2]) * 0.7071
    q = np.stack([a, b, np.zeros_like(a)], 1)
    d = _checker(q, 0.3, h.fw)
    col = _mix((0.88, 0.80, 0.62), (0.70, 0.58, 0.42), d)
    return col * (0.9 + 0.2 * _fbm(p, 0.4, 2, 4.0))[:, None]


def _mat_wall_south(h: _Hit) -> np.ndarray:
    """Green horizontal stripes of two widths."""
    p = h.p
    s1 = _stripes(p[:, 2], 0.30, h.fw, 0.5)
    s2 = _stripes(p[:, 2] + 0.05, 0.06, h.fw, 0.3)
    col = _mix((0.62, 0.76, 0.55), (0.36, 0.52, 0.36), s1)
    return col * (1 - 0.18 * s2 * (1 - s1))[:, None] * (0.92 + 0.16 * _fbm(p, 0.8, 2, 6.0))[:, None]


def _mat_wall_north(h: _Hit) -> np.ndarray:
    """Terracotta plaster with large colour blotches."""
    return _mat_noise((0.72, 0.38, 0.28), (0.96, 0.78, 0.56), 0.45, 3, 2.0)(h)


def _mat_beach_ball(h: _Hit) -> np.ndarray:
    palette = np.array(
        [(0.9, 0.1, 0.1), (0.95, 0.95, 0.95), (0.1, 0.3, 0.85), (0.98, 0.85, 0.1), (0.1, 0.6, 0.25), (0.95, 0.5, 0.1)],
        np.float32,
    )
    n = h.nl
    seg = np.floor((np.arctan2(n[:, 1], n[:, 0]) / (2 * np.pi) + 0.5) * 6).astype(np.int64) % 6
    col = palette[seg]
    cap = np.abs(n[:, 2]) > 0.9
    col[cap] = (0.97, 0.97, 0.97)
    return col


def _mat_clock(h: _Hit) -> np.ndarray:
    pl = h.pl
    r = np.hypot(pl[:, 0], pl[:, 1])
    ang = np.arctan2(pl[:, 1], pl[:, 0]) / (2 * np.pi) * 12
    ticks = _pulse(ang + 0.06, 0.12, h.fw / np.maximum(r, 0.02) * 12 / (2 * np.pi)) * (r > 0.14) * (r < 0.18)
    hand = ((np.abs(pl[:, 0]) < 0.008) & (pl[:, 1] > 0) & (pl[:, 1] < 0.13)) | (
        (np.abs(pl[:, 1] - 0.3 * pl[:, 0]) < 0.008) & (pl[:, 0] > 0) & (pl[:, 0] < 0.1)
    )
    col = _mix((0.96, 0.95, 0.9), (0.05, 0.05, 0.05), np.maximum(ticks, hand.astype(np.float32)))
    rim = (r > 0.185) | (h.face != 5)
    col[rim] = (0.55, 0.12, 0.12)
    return col


def _mat_painting(h: _Hit) -> np.ndarray:
    """An abstract painting: three colours mixed by two noise fields."""
    p = h.pl
    a = _fbm(p, 0.18, 3, 21.0)
    b = _fbm(p, 0.09, 2, 33.0)
    col = _mix((0.10, 0.25, 0.60), (0.95, 0.75, 0.15), np.clip(2.5 * (a - 0.5) + 0.5, 0, 1))
    return col * (1 - 0.6 * (b > 0.62))[:, None] + 0.6 * (b > 0.62)[:, None] * np.array([0.85, 0.15, 0.20], np.float32)


def _mat_poster(h: _Hit) -> np.ndarray:
    """A calendar-like poster: black-and-white grid of 10 cm squares under a red header."""
    p = h.pl
    grid = _checker(np.stack([p[:, 1], p[:, 2], np.zeros(len(p), np.float32)], 1), 0.1, h.fw)
    col = _mix((0.95, 0.95, 0.95), (0.08, 0.08, 0.08), grid)
    header = p[:, 2] > 0.3
    col[header] = (0.85, 0.12, 0.12)
    return col


def _mat_window(h: _Hit) -> np.ndarray:
    """A window: sky gradient behind a white frame with a cross bar."""
    p = h.pl
    sky = _mix((0.55, 0.75, 0.98), (0.92, 0.96, 1.0), np.clip(0.5 - p[:, 2] / 0.9, 0, 1))
    clouds = np.clip(2.2 * (_fbm(p, 0.25, 3, 44.0) - 0.55), 0, 1)
    sky = sky * (1 - clouds)[:, None] + clouds[:, None]
    frame = (np.abs(p[:, 0]) > 0.55) | (np.abs(p[:, 2]) > 0.4) | (np.abs(p[:, 0]) < 0.025) | (np.abs(p[:, 2]) < 0.025)
    sky[frame | (h.face != 3)] = (0.96, 0.96, 0.94)
    return sky


def _mat_rug(h: _Hit) -> np.ndarray:
    """A rug with concentric rectangular bands and a checker centre."""
    p = h.pl
    r = np.maximum(np.abs(p[:, 0]) - 0.35, np.abs(p[:, 1]))
    bands = _stripes(r, 0.14, h.fw, 0.5)
    col = _mix((0.65, 0.12, 0.16), (0.92, 0.86, 0.70), bands)
    centre = r < 0.3
    chk = _checker(p[centre], 0.1, h.fw[centre])
    col[centre] = _mix((0.10, 0.20, 0.45), (0.92, 0.86, 0.70), chk)
    return col * (0.85 + 0.3 * _fbm(p, 0.02, 1, 8.0))[:, None]


def _mat_angle_stripes(c0, c1, n: int) -> Material:
    """Vertical stripes around a cylinder's axis (n around), caps in c0."""

    def f(h):
        ang = np.arctan2(h.pl[:, 1], h.pl[:, 0]) / (2 * np.pi) * n
        col = _mix(c0, c1, _pulse(ang, 0.5, np.full(len(ang), 0.05, np.float32)))
        col[h.face != 6] = c0
        return col

    return f


def _mat_rings(c0, c1, period: float) -> Material:
    """Horizontal bands along a cylinder's (or box's) local z."""

    def f(h):
        return _mix(c0, c1, _stripes(h.pl[:, 2], period, h.fw, 0.5))

    return f


def _mat_book(i: int, half_height: float) -> Material:
    rng = np.random.default_rng(1000 + i)
    hue = rng.random()
    base = np.array([0.5 + 0.45 * math.cos(2 * math.pi * (hue + k / 3)) for k in range(3)], np.float32)
    base = np.clip(base * rng.uniform(0.55, 1.0), 0.05, 1.0)
    band_c = np.where(rng.random() < 0.5, np.float32(0.95), np.float32(0.1)) * np.ones(3, np.float32)
    band_z = rng.uniform(-0.6, 0.6)

    def f(h):
        zrel = h.pl[:, 2] / np.float32(half_height)
        band = np.abs(zrel - band_z) < 0.12
        col = np.broadcast_to(base, (len(h.p), 3)).copy()
        col[band] = band_c
        return col * (0.9 + 0.2 * _fbm(h.p, 0.05, 1, float(i)))[:, None]

    return f


# ------------------------------------------------------------------------------------------
# Geometry: primitives in a local frame (centre, rotation local->world); ray tests take the
# ray origin and directions in that local frame and return the hit distance t (inf on miss),
# in units of the direction vectors' length.
# ------------------------------------------------------------------------------------------

_EPS = 1e-6


@dataclass
class _Prim:
    kind: str  # "plane", "box", "sphere", "cylinder" (axis: local z)
    center: np.ndarray  # (3,) world (a plane: a point on it)
    size: np.ndarray  # (3,) box half extents; sphere (r, r, r); cylinder (r, r, half height);
    # plane: its unit normal, axis-aligned, pointing into free space
    R: np.ndarray  # (3, 3) local -> world (identity for planes)
    material: Material
    name: str = ""

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, float)
        self.size = np.asarray(self.size, float)
        self.axis_aligned = bool(np.array_equal(self.R, np.eye(3)))

    def corners(self) -> np.ndarray | None:
        """World corners (8, 3) of the local bounding box; None for an unbounded plane."""
        if self.kind == "plane":
            return None
        s = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * self.size
        return s @ self.R.T + self.center

    def intersect(self, o: np.ndarray, d: list[np.ndarray], inv: list[np.ndarray] | None) -> np.ndarray:
        """t of the first hit of rays o + t d (inf on a miss): o (3,) and d (3 arrays of one
        shape, the x, y, z components) in the local frame; inv: 1 / d when at hand."""
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if inv is None and self.kind in ("box", "plane"):
                inv = [np.float32(1.0) / dk for dk in d]
            if self.kind == "plane":
                axis = int(np.argmax(np.abs(self.size)))
                t = np.float32(-o[axis]) * inv[axis]
                return np.where(t > _EPS, t, np.float32(np.inf))
            if self.kind == "box":
                tnear = tfar = None
                for k in range(3):
                    t1 = np.float32(-self.size[k] - o[k]) * inv[k]
                    t2 = np.float32(self.size[k] - o[k]) * inv[k]
                    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
                    tnear = lo if tnear is None else np.maximum(tnear, lo)
                    tfar = hi if tfar is None else np.minimum(tfar, hi)
                return np.where((tnear <= tfar) & (tnear > _EPS), tnear, np.float32(np.inf))
            if self.kind == "sphere":
                r = self.size[0]
                a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                b = d[0] * np.float32(o[0]) + d[1] * np.float32(o[1]) + d[2] * np.float32(o[2])
                c = np.float32(o @ o - r * r)
                disc = b * b - a * c
                t = (-b - np.sqrt(disc)) / a
                return np.where((disc >= 0) & (t > _EPS), t, np.float32(np.inf))
            if self.kind == "cylinder":
                r, hz = self.size[0], self.size[2]
                dx, dy, dz = d
                a = dx * dx + dy * dy
                b = dx * np.float32(o[0]) + dy * np.float32(o[1])
                c = np.float32(o[0] ** 2 + o[1] ** 2 - r * r)
                disc = b * b - a * c
                ts = (-b - np.sqrt(disc)) / a
                zs = np.float32(o[2]) + ts * dz
                t = np.where((disc >= 0) & (ts > _EPS) & (np.abs(zs) <= hz), ts, np.float32(np.inf))
                if abs(o[2]) > hz:  # the cap facing the origin can be hit first
                    cap = hz if o[2] > 0 else -hz
                    tc = np.float32(cap - o[2]) / dz
                    xc, yc = np.float32(o[0]) + tc * dx, np.float32(o[1]) + tc * dy
                    t = np.where((tc > _EPS) & (xc * xc + yc * yc <= r * r) & (tc < t), tc, t)
                return t
        raise ValueError(self.kind)

    def surface(self, pl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local normals (n, 3) and face ids (n,) at local hit points (n, 3): box and plane
        faces 2 * axis + (normal > 0); cylinder caps 4 (-z) / 5 (+z), side 6; spheres 6."""
        n = np.zeros((len(pl), 3), np.float32)
        if self.kind == "plane":
            axis = int(np.argmax(np.abs(self.size)))
            n[:] = self.size
            return n, np.full(len(pl), 2 * axis + int(self.size[axis] > 0), np.int64)
        if self.kind == "box":
            rx, ry, rz = (np.abs(pl[:, k]) * np.float32(1.0 / self.size[k]) for k in range(3))
            axis = np.where((rx >= ry) & (rx >= rz), 0, np.where(ry >= rz, 1, 2))
            comp = np.choose(axis, [pl[:, 0], pl[:, 1], pl[:, 2]])
            positive = comp >= 0
            n[np.arange(len(pl)), axis] = np.where(positive, 1.0, -1.0)
            return n, 2 * axis + positive
        if self.kind == "sphere":
            return pl * np.float32(1.0 / self.size[0]), np.full(len(pl), 6, np.int64)
        r, hz = self.size[0], self.size[2]
        rad = np.hypot(pl[:, 0], pl[:, 1])
        is_cap = np.abs(np.abs(pl[:, 2]) - hz) < np.abs(rad - r)
        inv_rad = 1.0 / np.maximum(rad, 1e-9)
        n[:, 0] = np.where(is_cap, 0, pl[:, 0] * inv_rad)
        n[:, 1] = np.where(is_cap, 0, pl[:, 1] * inv_rad)
        n[:, 2] = np.where(is_cap, np.sign(pl[:, 2]), 0)
        face = np.where(is_cap, np.where(pl[:, 2] > 0, 5, 4), 6)
        return n, face.astype(np.int64)

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (m) from world points (n, 3) to the surface (> 0 in free space)."""
        pl = (p - self.center) @ self.R
        if self.kind == "plane":
            return pl @ self.size
        if self.kind == "box":
            q = np.abs(pl) - self.size
            return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
        if self.kind == "sphere":
            return np.linalg.norm(pl, axis=1) - self.size[0]
        dq = np.stack([np.hypot(pl[:, 0], pl[:, 1]) - self.size[0], np.abs(pl[:, 2]) - self.size[2]], 1)
        return np.linalg.norm(np.maximum(dq, 0), axis=1) + np.minimum(dq.max(axis=1), 0)


def _box(lo, hi, material, name="", R=None, pivot=None) -> _Prim:
    """Axis-aligned box from corners lo..hi; optionally rotated by R about `pivot` (world)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, s = (lo + hi) / 2, (hi - lo) / 2
    R = np.eye(3) if R is None else R
    if pivot is not None:
        c = R @ (c - pivot) + pivot
    return _Prim("box", c, s, R, material, name)


def _sphere(c, r, material, name="") -> _Prim:
    return _Prim("sphere", np.asarray(c, float), np.full(3, float(r)), np.eye(3), material, name)


def _cylinder(c, r, half_h, material, name="", R=None) -> _Prim:
    return _Prim(
        "cylinder", np.asarray(c, float), np.array([r, r, half_h], float), np.eye(3) if R is None else R, material, name
    )


#: The room: x in [-3, 3], y in [-2.5, 2.5], z in [0, 3] metres.
ROOM_LO = np.array([-3.0, -2.5, 0.0])
ROOM_HI = np.array([3.0, 2.5, 3.0])


def _build_scene() -> list[_Prim]:
    P: list[_Prim] = []
    # The room's six faces, seen from inside (planes with inward normals).
    walls = [
        ("west wall", _mat_wall_west),
        ("east wall", _mat_wall_east),
        ("south wall", _mat_wall_south),
        ("north wall", _mat_wall_north),
        ("floor", _mat_floor),
        ("ceiling", _mat_ceiling),
    ]
    for k, (name, mat) in enumerate(walls):
        axis, high = divmod(k, 2)
        point = (ROOM_LO + ROOM_HI) / 2
        point[axis] = ROOM_HI[axis] if high else ROOM_LO[axis]
        normal = np.zeros(3)
        normal[axis] = -1.0 if high else 1.0
        P.append(_Prim("plane", point, normal, np.eye(3), mat, name))

    # Sofa against the south wall.
    fabric = _mat_noise((0.45, 0.08, 0.10), (0.75, 0.22, 0.20), 0.12, 2, 1.4)
    P.append(_box((-1.95, -2.26, 0.0), (-0.05, -1.60, 0.42), fabric, "sofa seat"))
    P.append(_box((-2.15, -2.50, 0.0), (0.15, -2.26, 0.92), fabric, "sofa back"))
    P.append(_box((-2.15, -2.26, 0.0), (-1.95, -1.55, 0.62), fabric, "sofa arm"))
    P.append(_box((-0.05, -2.26, 0.0), (0.15, -1.55, 0.62), fabric, "sofa arm"))
    P.append(
        _box(
            (-1.80, -2.22, 0.42),
            (-1.35, -2.06, 0.80),
            _mat_checker((0.95, 0.75, 0.15), (0.35, 0.20, 0.05), 0.06),
            "cushion",
            _rot(8, 0, 12),
            np.array([-1.57, -2.14, 0.42]),
        )
    )
    P.append(
        _box(
            (-0.75, -2.22, 0.42),
            (-0.30, -2.06, 0.78),
            _mat_rings((0.2, 0.55, 0.65), (0.9, 0.9, 0.85), 0.05),
            "cushion",
            _rot(-10, 0, 10),
            np.array([-0.52, -2.14, 0.42]),
        )
    )

    # Table (rotated 15 deg) with legs, a ball, a mug and a book on it, east side.
    Rt, piv = _rot(15), np.array([1.95, 0.55, 0.0])
    wood = _mat_wood((0.45, 0.28, 0.14), (0.70, 0.48, 0.28), 0)
    P.append(_box((1.35, 0.15, 0.72), (2.55, 0.95, 0.77), wood, "table top", Rt, piv))
    metal = _mat_solid((0.18, 0.18, 0.20), 0.1, 0.1)
    for lx in (1.40, 2.45):
        for ly in (0.20, 0.85):
            P.append(_box((lx, ly, 0.0), (lx + 0.05, ly + 0.05, 0.72), metal, "table leg", Rt, piv))
    P.append(
        _sphere(
            Rt @ (np.array([2.25, 0.40, 0.0]) - piv) + piv + (0, 0, 0.89),
            0.12,
            _mat_checker((0.05, 0.05, 0.05), (0.95, 0.95, 0.95), 0.04),
            "ball",
        )
    )
    P.append(
        _cylinder(
            Rt @ (np.array([1.65, 0.75, 0.0]) - piv) + piv + (0, 0, 0.83),
            0.045,
            0.06,
            _mat_rings((0.8, 0.1, 0.1), (0.95, 0.95, 0.95), 0.03),
            "mug",
        )
    )
    P.append(_box((1.55, 0.30, 0.77), (1.85, 0.52, 0.82), _mat_solid((0.1, 0.45, 0.2)), "book", Rt @ _rot(20), piv))

    # Cabinet in the north-west corner: drawers, handles, a vase on top.
    P.append(
        _box(
            (-3.0, 1.35, 0.0), (-2.25, 2.5, 1.2), _mat_checker((0.85, 0.85, 0.82), (0.70, 0.72, 0.75), 0.15), "cabinet"
        )
    )
    for z0 in (0.08, 0.46, 0.84):
        P.append(_box((-2.25, 1.42, z0), (-2.22, 2.43, z0 + 0.32), _mat_solid((0.15, 0.45, 0.50), 0.12, 0.2), "drawer"))
        P.append(_box((-2.22, 1.80, z0 + 0.14), (-2.19, 2.05, z0 + 0.18), _mat_solid((0.8, 0.7, 0.3), 0.05), "handle"))
    P.append(
        _cylinder((-2.62, 1.92, 1.38), 0.10, 0.18, _mat_rings((0.15, 0.25, 0.70), (0.90, 0.90, 0.95), 0.06), "vase")
    )

    # Bookshelf against the north wall: sides, boards, books of varied sizes.
    dark = _mat_wood((0.25, 0.15, 0.08), (0.40, 0.26, 0.14), 0, 0.03)
    P.append(_box((0.20, 2.15, 0.0), (0.24, 2.5, 1.9), dark, "shelf side"))
    P.append(_box((1.76, 2.15, 0.0), (1.80, 2.5, 1.9), dark, "shelf side"))
    for z in (0.0, 0.5, 1.0, 1.45, 1.86):
        P.append(_box((0.24, 2.15, z), (1.76, 2.5, z + 0.04), dark, "shelf board"))
    rng = np.random.default_rng(7)
    nb = 0
    for z in (0.04, 0.54, 1.04):
        x = 0.27 + rng.uniform(0, 0.1)
        while True:
            w = rng.uniform(0.04, 0.12) * (3 if rng.random() < 0.15 else 1)
            hgt = rng.uniform(0.22, 0.40)
            dep = rng.uniform(0.16, 0.28)
            if x + w > 1.72:
                break
            if rng.random() < 0.8:
                P.append(_box((x, 2.48 - dep, z), (x + w, 2.48, z + hgt), _mat_book(nb, hgt / 2), "book"))
                nb += 1
            x += w + rng.uniform(0.0, 0.03)
    P.append(_sphere((1.2, 2.33, 1.49 + 0.11), 0.11, _mat_noise((0.1, 0.5, 0.3), (0.8, 0.9, 0.3), 0.05, 2), "globe"))

    # Floor lamp in the south-east corner, a stool, a big beach ball, a rug.
    P.append(_cylinder((2.45, -1.95, 0.015), 0.18, 0.015, metal, "lamp base"))
    P.append(_cylinder((2.45, -1.95, 0.76), 0.022, 0.73, metal, "lamp pole"))
    P.append(
        _cylinder(
            (2.45, -1.95, 1.62),
            0.20,
            0.15,
            _mat_angle_stripes((0.95, 0.90, 0.75), (0.80, 0.65, 0.45), 12),
            "lamp shade",
        )
    )
    P.append(
        _cylinder(
            (1.10, -1.25, 0.23), 0.20, 0.23, _mat_angle_stripes((0.95, 0.55, 0.10), (0.25, 0.15, 0.60), 8), "stool"
        )
    )
    P.append(_sphere((-0.95, 1.15, 0.30), 0.30, _mat_beach_ball, "beach ball"))
    P.append(_box((-1.3, -1.1, 0.0), (0.7, 0.6, 0.012), _mat_rug, "rug"))

    # On the walls: painting and radiator (west), poster and door (east), window (south),
    # clock (north); a beam and a lamp on the ceiling.
    P.append(_box((-3.0, -0.65, 1.15), (-2.96, 0.65, 2.05), _mat_solid((0.3, 0.2, 0.1), 0.05), "picture frame"))
    P.append(_box((-2.96, -0.58, 1.22), (-2.95, 0.58, 1.98), _mat_painting, "painting"))
    P.append(_box((-3.0, -0.8, 0.15), (-2.9, 0.8, 0.70), _radiator, "radiator"))
    P.append(_box((2.99, -1.55, 1.0), (3.0, -0.55, 2.0), _mat_poster, "poster"))
    P.append(
        _box((2.95, 0.95, 0.0), (3.0, 1.95, 2.1), _mat_wood((0.55, 0.36, 0.20), (0.75, 0.55, 0.35), 2, 0.05), "door")
    )
    P.append(_sphere((2.91, 1.80, 1.0), 0.035, _mat_solid((0.85, 0.75, 0.35), 0.03), "door knob"))
    P.append(_box((-1.6, -2.5, 1.25), (-0.4, -2.47, 2.15), _mat_window, "window"))
    P.append(_box((-1.68, -2.5, 1.19), (-0.32, -2.38, 1.25), _mat_solid((0.95, 0.95, 0.93), 0.05), "window sill"))
    P.append(_cylinder((-1.0, 2.47, 2.05), 0.2, 0.03, _mat_clock, "clock", _rot(0, 0, 90)))
    P.append(
        _box((-1.65, -2.5, 2.8), (-1.4, 2.5, 3.0), _mat_wood((0.50, 0.32, 0.18), (0.68, 0.46, 0.26), 1, 0.05), "beam")
    )
    P.append(_sphere((0.6, 0.2, 2.78), 0.17, _mat_solid((1.0, 0.97, 0.85), 0.02), "ceiling lamp"))
    return P


def _radiator(h: _Hit) -> np.ndarray:
    """White radiator with vertical fins (every 6 cm) and a grey top edge."""
    fins = _stripes(h.p[:, 1], 0.06, h.fw, 0.4)
    col = _mix((0.96, 0.96, 0.95), (0.62, 0.62, 0.66), fins)
    col[h.face == 5] = (0.55, 0.55, 0.58)
    return col


_SCENE: list[_Prim] | None = None
_SCENE_LOCK = threading.Lock()

#: Light: a fixed direction (towards the light), Lambertian with ambient term.
_LIGHT = np.array([0.35, -0.25, 0.90]) / np.linalg.norm([0.35, -0.25, 0.90])
_AMBIENT, _DIFFUSE = 0.60, 0.45
#: Shading overrides for self-lit surfaces (names).
_UNLIT = {"ceiling lamp", "window"}


def scene() -> list[_Prim]:
    """The scene's primitives (built once)."""
    global _SCENE
    with _SCENE_LOCK:
        if _SCENE is None:
            _SCENE = _build_scene()
        return _SCENE


def scene_clearance(points: np.ndarray) -> np.ndarray:
    """Distance in metres from world points (n, 3) to the nearest surface of the scene."""
    points = np.asarray(points, float).reshape(-1, 3)
    return np.min([p.sdf(points) for p in scene()], axis=0)


# ------------------------------------------------------------------------------------------
# Rendering
# ------------------------------------------------------------------------------------------


_BOX_EDGES = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]


def _screen_rect(corners_cam: np.ndarray, camera: Camera, near: float = 0.02) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (v0, v1, u0, u1) bounding the projection of a box given by its 8
    camera-frame corners (clipped at z = near), or None when it is out of view."""
    z = corners_cam[:, 2]
    front = z > near
    if not front.any():
        return None
    pts = [corners_cam[front]]
    if not front.all():  # add where the box's edges cross the near plane
        for i, j in _BOX_EDGES:
            if front[i] != front[j]:
                a, b = corners_cam[i], corners_cam[j]
                pts.append((a + (near - a[2]) / (b[2] - a[2]) * (b - a))[None])
    pts = np.concatenate(pts)
    uu = camera.fx * pts[:, 0] / pts[:, 2] + camera.cx
    vv = camera.fy * pts[:, 1] / pts[:, 2] + camera.cy
    v0 = max(0, int(np.floor(vv.min())) - 1)
    v1 = min(camera.height, int(np.ceil(vv.max())) + 2)
    u0 = max(0, int(np.floor(uu.min())) - 1)
    u1 = min(camera.width, int(np.ceil(uu.max())) + 2)
    return (v0, v1, u0, u1) if v0 < v1 and u0 < u1 else None


def render(camera: Camera, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Render the scene from `pose` (camera-to-world, OpenCV axes): (HxWx3 uint8 rgb,
    HxW float32 depth in metres, the camera-frame z of the nearest hit)."""
    prims = scene()
    H, W = camera.height, camera.width
    R = pose[:3, :3].astype(np.float64)
    o = pose[:3, 3].astype(np.float64)
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    xc = (u - np.float32(camera.cx)) / np.float32(camera.fx)
    yc = (v - np.float32(camera.cy)) / np.float32(camera.fy)
    # World directions with camera-frame z = 1: the hit distance t is the depth itself.
    Rf = R.astype(np.float32)
    dw = [Rf[k, 0] * xc + Rf[k, 1] * yc + Rf[k, 2] for k in range(3)]
    with np.errstate(divide="ignore"):
        invw = [np.float32(1.0) / dk for dk in dw]

    tbest = np.full((H, W), np.inf, np.float32)
    ids = np.zeros((H, W), np.int16)
    for k, prim in enumerate(prims):
        corners = prim.corners()
        if corners is None:
            rect = (0, H, 0, W)
        else:
            rect = _screen_rect((corners - o) @ R, camera)
            if rect is None:
                continue
        v0, v1, u0, u1 = rect
        ol = (o - prim.center) @ prim.R
        if prim.axis_aligned:
            d = [dk[v0:v1, u0:u1] for dk in dw]
            inv = [ik[v0:v1, u0:u1] for ik in invw]
        else:
            Rp = prim.R.astype(np.float32)
            sub = [dk[v0:v1, u0:u1] for dk in dw]
            d = [Rp[0, j] * sub[0] + Rp[1, j] * sub[1] + Rp[2, j] * sub[2] for j in range(3)]
            inv = None
        t = prim.intersect(ol, d, inv)
        tb = tbest[v0:v1, u0:u1]
        better = t < tb
        if better.any():
            tb[better] = t[better]
            ids[v0:v1, u0:u1][better] = k

    # Shade, one primitive at a time. Points are kept as (3, n) planes and handed to materials
    # as their (n, 3) transposes, so that p[:, k] is contiguous.
    tflat = tbest.ravel()
    idflat = ids.ravel()
    dflat = [dk.ravel() for dk in dw]
    order = np.argsort(idflat, kind="stable")
    counts = np.bincount(idflat, minlength=len(prims))
    starts = np.concatenate([[0], np.cumsum(counts)])
    rgb = np.empty((3, H * W), np.float32)
    inv_f = np.float32(1.5 / max(camera.fx, camera.fy))  # pixel footprint (m) per metre of depth
    light = _LIGHT.astype(np.float32)
    for k in np.nonzero(counts)[0]:
        prim = prims[k]
        pix = order[starts[k] : starts[k + 1]]
        t = np.take(tflat, pix)
        P = np.empty((3, len(pix)), np.float32)
        for j in range(3):
            P[j] = np.float32(o[j]) + t * np.take(dflat[j], pix)
        Pl = P - prim.center.astype(np.float32)[:, None]
        if not prim.axis_aligned:
            Pl = prim.R.T.astype(np.float32) @ Pl
        nl, face = prim.surface(Pl.T)
        col = prim.material(_Hit(P.T, Pl.T, nl, face, t * inv_f))
        if prim.name in _UNLIT:
            shade = np.float32(1.0)
        else:
            nw_dot_l = nl @ (prim.R.T.astype(np.float32) @ light)
            shade = np.float32(_AMBIENT) + np.float32(_DIFFUSE) * np.maximum(nw_dot_l, 0.0)
        col = (col * (shade[:, None] if np.ndim(shade) else shade)).T
        for j in range(3):
            np.put(rgb[j], pix, col[j])
    rgb = rgb.T
    rgb8 = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8).reshape(H, W, 3)
    return rgb8, tbest


# ------------------------------------------------------------------------------------------
# Camera path
# ------------------------------------------------------------------------------------------

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


# ------------------------------------------------------------------------------------------
# The dataset
# ------------------------------------------------------------------------------------------


def _write_npz(f, arrays) -> None:
    """Write (name, array) pairs as an .npz that np.load reads, like np.savez_compressed but
    streaming and with zlib level 1 (the frames compress nearly as well, twice as fast)."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, value in arrays:
            with zf.open(name + ".npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def default_cache_dir() -> Path:
    root = os.environ.get("SLAMKIT_CACHE")
    return Path(root) / "synthetic" if root else Path.home() / ".cache" / "slamkit" / "synthetic"


class SyntheticDataset(Dataset):
    """The generated furnished-room sequence (see the module docstring). Frames: rgb HxWx3
    uint8, depth HxW float32 metres (exact unless depth_noise / depth_dropout), gt_pose
    camera-to-world, timestamp raw_index / 30 s."""

    # small frames (320x240 by default) of a 6 x 5 x 3 m room: a dense sample stride
    default_sensor = SensorProfile(depth_scale=DEPTH_SCALE, depth_trunc=6.0, max_gaussian_scale=0.5,
                                   tracking_pixel_stride=2, min_target_opacity=0.05)

    def __init__(self, cfg: SyntheticConfig):
        super().__init__(cfg)
        self.cfg: SyntheticConfig = cfg
        fx = (cfg.width / 2.0) / math.tan(math.radians(cfg.fov_deg) / 2.0)
        self._camera = Camera(cfg.width, cfg.height, fx, fx, (cfg.width - 1) / 2.0, (cfg.height - 1) / 2.0)
        self._lock = threading.Lock()
        self._store = None  # NpzFile or dict: rgb_%05d (uint8), depth_%05d (uint16), poses
        self.cache_path = Path(cfg.cache_dir).expanduser() if cfg.cache_dir else default_cache_dir()
        self.cache_path = self.cache_path / f"synthetic_{self.cache_key()[:20]}.npz"
        self._open_or_generate()

    # -- cache ----------------------------------------------------------------------------
    def generation_params(self) -> dict:
        c = self.cfg
        return {
            "version": GENERATOR_VERSION,
            "num_frames": int(c.num_frames),
            "width": int(c.width),
            "height": int(c.height),
            "fov_deg": float(c.fov_deg),
            "seed": int(c.seed),
            "speed": float(c.speed),
        }

    def cache_key(self) -> str:
        return hashlib.sha256(json.dumps(self.generation_params(), sort_keys=True).encode()).hexdigest()

    def _open_or_generate(self) -> None:
        meta = json.dumps(self.generation_params(), sort_keys=True)
        if self._open_cache(meta):
            return
        t0 = time.perf_counter()
        tmp = None
        try:
            self.cache_path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.cache_path.parent, prefix=self.cache_path.stem + ".", suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                _write_npz(f, self._generate(meta))
            os.replace(tmp, self.cache_path)  # atomic: readers never see a partial file
            tmp = None
        except OSError as e:
            log.warning("cannot write the synthetic cache %s (%s); keeping the sequence in memory", self.cache_path, e)
            self._store = dict(self._generate(meta))
            self._poses = self._store["poses"]
            return
        finally:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
        log.info(
            "generated the synthetic sequence (%d frames, %dx%d) in %.1f s: %s",
            self.cfg.num_frames,
            self.cfg.width,
            self.cfg.height,
            time.perf_counter() - t0,
            self.cache_path,
        )
        if not self._open_cache(meta):
            raise DataError(f"{self.cache_path}: the synthetic sequence just written cannot be read back")

    def _open_cache(self, meta: str) -> bool:
        """Open the cache file if it exists and holds this parameter set."""
        if not self.cache_path.is_file():
            return False
        try:
            store = np.load(self.cache_path)
            if str(store["meta"]) == meta and f"depth_{self.cfg.num_frames - 1:05d}.npy" in store.zip.namelist():
                self._poses = store["poses"]
                self._store = store
                return True
            store.close()
            log.warning("synthetic cache %s does not match its parameters; regenerating", self.cache_path)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
            log.warning("synthetic cache %s is unreadable (%s); regenerating", self.cache_path, e)
        return False

    def _generate(self, meta: str):
        """Yield (name, array): meta, poses, then rgb_%05d (uint8) and depth_%05d (uint16,
        DEPTH_SCALE units per metre) per frame."""
        c = self.cfg
        poses = camera_path(c.num_frames, c.seed, c.speed)
        yield "meta", np.array(meta)
        yield "poses", poses
        # Frames are independent: render a chunk at a time on a few threads (numpy releases
        # the GIL); only one chunk is held in memory.
        workers = max(1, min(4, os.cpu_count() or 1))
        with ThreadPoolExecutor(workers) as pool:
            for start in range(0, len(poses), 16):
                chunk = pool.map(lambda pose: render(self._camera, pose), poses[start : start + 16])
                for i, (rgb, depth) in enumerate(chunk, start):
                    yield f"rgb_{i:05d}", rgb
                    yield f"depth_{i:05d}", np.clip(np.round(depth * DEPTH_SCALE), 0, 65535).astype(np.uint16)

    def close(self) -> None:
        """Close the cache file (frames cannot be loaded afterwards)."""
        if hasattr(self._store, "close"):
            self._store.close()
        self._store = None

    def __getstate__(self) -> dict:  # picklable (e.g. for a worker process): reopen there
        state = self.__dict__.copy()
        state["_store"] = state["_lock"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
        self._open_or_generate()

    # -- Dataset --------------------------------------------------------------------------
    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return int(self.cfg.num_frames)

    def load(self, raw_index: int) -> Frame:
        if not 0 <= raw_index < self.cfg.num_frames:
            raise IndexError(f"synthetic frame {raw_index} out of range [0, {self.cfg.num_frames})")
        with self._lock:
            rgb = np.array(self._store[f"rgb_{raw_index:05d}"])
            depth_raw = self._store[f"depth_{raw_index:05d}"]
        depth = depth_raw.astype(np.float32) / np.float32(DEPTH_SCALE)
        c = self.cfg
        if c.depth_noise > 0 or c.depth_dropout > 0:
            rng = np.random.default_rng([c.seed, raw_index, 0xDE])
            valid = depth > 0
            if c.depth_noise > 0:
                noise = rng.standard_normal(depth.shape).astype(np.float32) * np.float32(c.depth_noise) * depth * depth
                depth = np.where(valid, np.maximum(depth + noise, 1e-3), 0).astype(np.float32)
            if c.depth_dropout > 0:
                depth[rng.random(depth.shape) < c.depth_dropout] = 0.0
        return Frame(
            index=raw_index,
            timestamp=raw_index / FPS,
            rgb=rgb,
            depth=depth,
            camera=self._camera,
            gt_pose=np.array(self._poses[raw_index], dtype=np.float64),
        )
