"""Materials of the synthetic scene: functions of a `Hit` -> (n, 3) float32 RGB in [0, 1],
before shading. The factories (`mat_solid`, `mat_wood`, ...) return a material for given colours
and scales (metres); the others colour one surface of the scene each.
"""

from __future__ import annotations

import math

import numpy as np

from slamkit_plugins.datasets.synthetic.primitives import Hit, Material
from slamkit_plugins.datasets.synthetic.textures import checker, fbm, hash01, mix, pulse, stripes


def mat_solid(c, noise_amp: float = 0.08, scale: float = 0.3) -> Material:
    """Colour c (RGB in [0, 1]) varied by +- noise_amp with world-space noise of ~scale m features."""

    def f(h):
        return np.asarray(c, np.float32) * (1 - noise_amp + 2 * noise_amp * fbm(h.p, scale, 2))[:, None]

    return f


def mat_checker(c0, c1, cell: float, noise_amp: float = 0.06) -> Material:
    """3D checkerboard of c0 and c1 with `cell` m cells in the local frame, faint noise on top."""

    def f(h):
        col = mix(c0, c1, checker(h.pl, cell, h.fw))
        return col * (1 - noise_amp + 2 * noise_amp * fbm(h.p, 0.25, 1, 3.0))[:, None]

    return f


def mat_noise(c0, c1, scale: float, octaves: int = 3, contrast: float = 1.6) -> Material:
    """Blotches: c0 and c1 mixed by local-frame fractal noise of ~scale m features."""

    def f(h):
        n = np.clip(0.5 + contrast * (fbm(h.pl, scale, octaves, 11.0) - 0.5), 0, 1)
        return mix(c0, c1, n)

    return f


def mat_wood(c0, c1, grain_axis: int = 0, ring: float = 0.035) -> Material:
    """Wood: noise-warped stripes across the grain plus fine streaks along it."""
    stretch = np.full(3, 0.02, np.float32)
    stretch[grain_axis] = 0.6

    def f(h):
        q = h.pl
        other = [k for k in range(3) if k != grain_axis]
        d = q[:, other[0]] + 0.6 * q[:, other[1]] + 0.08 * fbm(q, 0.5, 2, 5.0)
        rings = stripes(d, ring, h.fw, 0.35)
        streak = fbm(q, stretch, 2, 17.0)
        return mix(c0, c1, np.clip(0.55 * rings + 0.8 * (streak - 0.5) + 0.25, 0, 1))

    return f


def mat_floor(h: Hit) -> np.ndarray:
    """Wooden planks along x, 0.18 m wide, with staggered ends, seams and grain."""
    p = h.p
    plank = np.floor(p[:, 1] / 0.18)
    r = hash01(plank, 1)
    end_u = p[:, 0] / 1.3 + r
    board = np.floor(end_u) * 97 + plank
    tint = hash01(board, 2)
    grain = fbm(p + tint[:, None] * 3.0, np.array([0.7, 0.012, 0.012], np.float32), 2, 2.0)
    base = mix((0.50, 0.33, 0.19), (0.74, 0.54, 0.33), np.clip(0.3 + 0.5 * tint + 0.7 * (grain - 0.5), 0, 1))
    seam = np.maximum(stripes(p[:, 1] - 0.005, 0.18, h.fw, 0.05), stripes(end_u * 1.3 - 0.005, 1.3, h.fw, 0.01))
    return base * (1.0 - 0.6 * seam)[:, None]


def mat_ceiling(h: Hit) -> np.ndarray:
    """Acoustic ceiling tiles: 0.6 m squares, grey grid lines, faint speckle."""
    p = h.p
    lines = np.maximum(stripes(p[:, 0] + 0.01, 0.6, h.fw, 0.035), stripes(p[:, 1] + 0.01, 0.6, h.fw, 0.035))
    speckle = fbm(p, 0.05, 2, 9.0)
    base = mix((0.80, 0.80, 0.78), (0.95, 0.94, 0.90), speckle)
    return base * (1 - 0.45 * lines)[:, None]


def mat_wall_west(h: Hit) -> np.ndarray:
    """Blue plaster above a white wainscot with vertical boards, a dark dado rail at 0.9 m."""
    p = h.p
    upper = mix((0.42, 0.55, 0.72), (0.62, 0.74, 0.86), fbm(p, 0.6, 3, 1.0))
    boards = mix((0.93, 0.92, 0.88), (0.70, 0.70, 0.68), stripes(p[:, 1], 0.12, h.fw, 0.12))
    lower = (p[:, 2] < 0.9).astype(np.float32)
    col = upper * (1 - lower)[:, None] + boards * lower[:, None]
    rail = np.clip(1.0 - np.abs(p[:, 2] - 0.9) / 0.03, 0, 1)
    return col * (1 - 0.7 * rail)[:, None]


def mat_wall_east(h: Hit) -> np.ndarray:
    """Beige wallpaper with a diamond pattern."""
    p = h.p
    a = (p[:, 1] + p[:, 2]) * 0.7071
    b = (p[:, 1] - p[:, 2]) * 0.7071
    q = np.stack([a, b, np.zeros_like(a)], 1)
    d = checker(q, 0.3, h.fw)
    col = mix((0.88, 0.80, 0.62), (0.70, 0.58, 0.42), d)
    return col * (0.9 + 0.2 * fbm(p, 0.4, 2, 4.0))[:, None]


def mat_wall_south(h: Hit) -> np.ndarray:
    """Green horizontal stripes of two widths."""
    p = h.p
    s1 = stripes(p[:, 2], 0.30, h.fw, 0.5)
    s2 = stripes(p[:, 2] + 0.05, 0.06, h.fw, 0.3)
    col = mix((0.62, 0.76, 0.55), (0.36, 0.52, 0.36), s1)
    return col * (1 - 0.18 * s2 * (1 - s1))[:, None] * (0.92 + 0.16 * fbm(p, 0.8, 2, 6.0))[:, None]


def mat_wall_north(h: Hit) -> np.ndarray:
    """Terracotta plaster with large colour blotches."""
    return mat_noise((0.72, 0.38, 0.28), (0.96, 0.78, 0.56), 0.45, 3, 2.0)(h)


def mat_beach_ball(h: Hit) -> np.ndarray:
    """Six coloured segments around the local z axis, white caps at the poles."""
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


def mat_clock(h: Hit) -> np.ndarray:
    """A clock face on the +z cap (ticks every hour, two hands), a dark red rim elsewhere."""
    pl = h.pl
    r = np.hypot(pl[:, 0], pl[:, 1])
    ang = np.arctan2(pl[:, 1], pl[:, 0]) / (2 * np.pi) * 12
    ticks = pulse(ang + 0.06, 0.12, h.fw / np.maximum(r, 0.02) * 12 / (2 * np.pi)) * (r > 0.14) * (r < 0.18)
    hand = ((np.abs(pl[:, 0]) < 0.008) & (pl[:, 1] > 0) & (pl[:, 1] < 0.13)) | (
        (np.abs(pl[:, 1] - 0.3 * pl[:, 0]) < 0.008) & (pl[:, 0] > 0) & (pl[:, 0] < 0.1)
    )
    col = mix((0.96, 0.95, 0.9), (0.05, 0.05, 0.05), np.maximum(ticks, hand.astype(np.float32)))
    rim = (r > 0.185) | (h.face != 5)
    col[rim] = (0.55, 0.12, 0.12)
    return col


def mat_painting(h: Hit) -> np.ndarray:
    """An abstract painting: three colours mixed by two noise fields."""
    p = h.pl
    a = fbm(p, 0.18, 3, 21.0)
    b = fbm(p, 0.09, 2, 33.0)
    col = mix((0.10, 0.25, 0.60), (0.95, 0.75, 0.15), np.clip(2.5 * (a - 0.5) + 0.5, 0, 1))
    return col * (1 - 0.6 * (b > 0.62))[:, None] + 0.6 * (b > 0.62)[:, None] * np.array([0.85, 0.15, 0.20], np.float32)


def mat_poster(h: Hit) -> np.ndarray:
    """A calendar-like poster: black-and-white grid of 10 cm squares under a red header."""
    p = h.pl
    grid = checker(np.stack([p[:, 1], p[:, 2], np.zeros(len(p), np.float32)], 1), 0.1, h.fw)
    col = mix((0.95, 0.95, 0.95), (0.08, 0.08, 0.08), grid)
    header = p[:, 2] > 0.3
    col[header] = (0.85, 0.12, 0.12)
    return col


def mat_window(h: Hit) -> np.ndarray:
    """A window: sky gradient behind a white frame with a cross bar."""
    p = h.pl
    sky = mix((0.55, 0.75, 0.98), (0.92, 0.96, 1.0), np.clip(0.5 - p[:, 2] / 0.9, 0, 1))
    clouds = np.clip(2.2 * (fbm(p, 0.25, 3, 44.0) - 0.55), 0, 1)
    sky = sky * (1 - clouds)[:, None] + clouds[:, None]
    frame = (np.abs(p[:, 0]) > 0.55) | (np.abs(p[:, 2]) > 0.4) | (np.abs(p[:, 0]) < 0.025) | (np.abs(p[:, 2]) < 0.025)
    sky[frame | (h.face != 3)] = (0.96, 0.96, 0.94)
    return sky


def mat_rug(h: Hit) -> np.ndarray:
    """A rug with concentric rectangular bands and a checker centre."""
    p = h.pl
    r = np.maximum(np.abs(p[:, 0]) - 0.35, np.abs(p[:, 1]))
    bands = stripes(r, 0.14, h.fw, 0.5)
    col = mix((0.65, 0.12, 0.16), (0.92, 0.86, 0.70), bands)
    centre = r < 0.3
    chk = checker(p[centre], 0.1, h.fw[centre])
    col[centre] = mix((0.10, 0.20, 0.45), (0.92, 0.86, 0.70), chk)
    return col * (0.85 + 0.3 * fbm(p, 0.02, 1, 8.0))[:, None]


def mat_angle_stripes(c0, c1, n: int) -> Material:
    """Vertical stripes around a cylinder's axis (n around), caps in c0."""

    def f(h):
        ang = np.arctan2(h.pl[:, 1], h.pl[:, 0]) / (2 * np.pi) * n
        col = mix(c0, c1, pulse(ang, 0.5, np.full(len(ang), 0.05, np.float32)))
        col[h.face != 6] = c0
        return col

    return f


def mat_rings(c0, c1, period: float) -> Material:
    """Horizontal bands along a cylinder's (or box's) local z."""

    def f(h):
        return mix(c0, c1, stripes(h.pl[:, 2], period, h.fw, 0.5))

    return f


def mat_book(i: int, half_height: float) -> Material:
    """Book spine number i: a colour and a light or dark band drawn from i; half_height in metres."""
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
        return col * (0.9 + 0.2 * fbm(h.p, 0.05, 1, float(i)))[:, None]

    return f


def mat_radiator(h: Hit) -> np.ndarray:
    """White radiator with vertical fins (every 6 cm) and a grey top edge."""
    fins = stripes(h.p[:, 1], 0.06, h.fw, 0.4)
    col = mix((0.96, 0.96, 0.95), (0.62, 0.62, 0.66), fins)
    col[h.face == 5] = (0.55, 0.55, 0.58)
    return col
