"""Procedural textures of the synthetic scene, vectorised over hit points.

Inputs: points (n, 3) float32 in metres (world or a primitive's local frame); `fw` (n,) the
footprint of a pixel in metres (patterns are box-filtered over it, so fine patterns fade to their
mean colour at a distance instead of aliasing). Outputs: (n,) weights in [0, 1] or (n, 3) RGB
colours in [0, 1].
"""

from __future__ import annotations

import numpy as np

from slamkit_plugins.datasets.synthetic.primitives import rotation_deg

_NOISE_N = 32  # value-noise lattice period (cells)
_NOISE_TABLE = np.random.default_rng(918273).random(_NOISE_N**3).astype(np.float32)

# Fixed rotations decorrelate the octaves of the noise (and hide the lattice's axes).
_OCTAVE_ROT32 = [
    r.astype(np.float32)
    for r in (rotation_deg(0, 0, 0), rotation_deg(37, 21, 11), rotation_deg(-53, 47, -29), rotation_deg(71, -13, 59))
]


def value_noise(qx: np.ndarray, qy: np.ndarray, qz: np.ndarray) -> np.ndarray:
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


def fbm(p: np.ndarray, scale: float | np.ndarray, octaves: int = 2, offset: float = 0.0) -> np.ndarray:
    """Fractal value noise in [0, 1] at points p (n, 3): `octaves` octaves, the first with
    features ~`scale` m (a 3-vector scale stretches the noise, e.g. wood grain)."""
    sc = np.broadcast_to(np.asarray(scale, np.float32), (3,))
    cols = [p[:, k] * np.float32(1.0 / sc[k]) for k in range(3)]
    total, amp, norm = None, 1.0, 0.0
    for o in range(octaves):
        M = _OCTAVE_ROT32[o % 4] * np.float32(2.0**o)
        off = np.float32(offset + 7.31 * o)
        q = [cols[0] * M[0, j] + cols[1] * M[1, j] + cols[2] * M[2, j] + off for j in range(3)]
        n = value_noise(*q)
        total = n if total is None else total + np.float32(amp) * n
        norm += amp
        amp *= 0.5
    return total * np.float32(1.0 / norm)


def pulse(u: np.ndarray, duty: float, w: np.ndarray) -> np.ndarray:
    """Box-filtered pulse train: 1 where frac(u) < duty, else 0, averaged over a window of
    width w (all in periods)."""
    w = np.maximum(w, 0.02)

    def integral(x):
        fl = np.floor(x)
        return fl * duty + np.minimum(x - fl, duty)

    return np.clip((integral(u + 0.5 * w) - integral(u - 0.5 * w)) / w, 0.0, 1.0)


def stripes(x: np.ndarray, period: float, fw: np.ndarray, duty: float = 0.5) -> np.ndarray:
    """Box-filtered stripes across x (metres): 1 on the first `duty` of every `period` metres."""
    return pulse(x / period, duty, fw / period)


def checker(p: np.ndarray, cell: float, fw: np.ndarray) -> np.ndarray:
    """3D checkerboard with cells of `cell` metres (0 / 1), box-filtered."""
    s = np.ones(len(p), np.float32)
    for k in range(3):
        s *= 2.0 * pulse(p[:, k] / (2 * cell) + 0.123 * (k + 1), 0.5, fw / (2 * cell)) - 1.0
    return 0.5 - 0.5 * s


def mix(c0, c1, t: np.ndarray) -> np.ndarray:
    """Blend of two RGB colours by weights t (n,) in [0, 1]: (n, 3)."""
    c0, c1 = np.asarray(c0, np.float32), np.asarray(c1, np.float32)
    return c0 + (c1 - c0) * t[:, None]


def hash01(i: np.ndarray, salt: int = 0) -> np.ndarray:
    """Pseudo-random value in [0, 1) per integer."""
    h = (i.astype(np.int64) * 0x2C1B3C6D + salt * 0x297A2D39) & 0xFFFFFFFF
    h ^= h >> 15
    h = (h * 0x297A2D39) & 0xFFFFFFFF
    h ^= h >> 12
    return (h & 0xFFFF).astype(np.float32) / 65536.0
