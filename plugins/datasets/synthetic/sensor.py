"""A structured-light RGB-D sensor's errors, applied to an exact rendered frame (Kinect v1-like
by default; `SensorModel`'s fields give the sources of their values).

Depth, per pixel of the exact depth z (metres) seen at incidence angle theta (between the view
ray and the surface normal, from the exact depth's neighbours):

1. axial noise, Gaussian with sigma(z, theta) = a + b (z - 0.4)^2 + 1e-4 / sqrt(z) * theta^2 /
   (pi/2 - theta)^2 metres (Nguyen, Izadi and Lovell 2012, fitted to a Kinect v1: a = 1.2 mm,
   b = 1.9 mm/m^2; it grows with the square of the distance, as Khoshelham and Elberink 2012
   found, and at grazing angles);
2. disparity quantisation: the sensor measures disparity d = f b / z (f the IR camera's focal
   length in pixels, b the projector-camera baseline) in steps of 1/8 pixel, so depth comes in
   steps of about z^2 / (8 f b): 2.9 mm at 1 m, 2.6 cm at 3 m for f = 580 px, b = 7.5 cm
   (Khoshelham and Elberink 2012);
3. missing depth where the projected pattern cannot be matched: at depth discontinuities (the
   projector's shadow and the correlation window straddling the edge: a band of pixels on both
   sides), on surfaces seen at grazing incidence (theta above a bound), and on dark surfaces
   (little infrared comes back: dropped at random, the darker the likelier).

Colour: Gaussian noise per channel in 8-bit levels.

Everything is vectorised numpy over the frame, and random draws come from the generator given,
so a frame's errors are the same every time it is loaded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorModel:
    """The structured-light model's parameters; their defaults, with their sources, are the
    synthetic dataset's config fields (`SyntheticConfig.sensor_model`)."""

    axial_sigma_m: float  # metres, a
    axial_sigma_per_m2: float  # metres per square metre, b
    focal_px: float  # the IR camera's focal length, pixels
    baseline_m: float  # projector to IR camera, metres
    disparity_step_px: float  # pixels
    edge_jump: float  # relative depth step between neighbouring pixels that makes an edge
    edge_band_px: int  # pixels lost on each side of an edge
    max_incidence_deg: float  # degrees: steeper, no depth
    dark_level: float  # grey level (0-1) below which depth may go missing, surely at black
    colour_sigma: float  # 8-bit levels per channel


def _shift(a: np.ndarray, dv: int, du: int) -> np.ndarray:
    """`a` moved by (dv, du) pixels, the edge rows / columns repeated (no wrap-around)."""
    h, w = a.shape[:2]
    v = np.clip(np.arange(h) - dv, 0, h - 1)
    u = np.clip(np.arange(w) - du, 0, w - 1)
    return a[v][:, u]


def incidence(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(H,W) radians between each pixel's view ray and the surface normal estimated from the
    depth's central differences (pi/2 where the depth or a neighbour is missing)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    points = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], axis=-1)
    du = _shift(points, 0, -1) - _shift(points, 0, 1)
    dv = _shift(points, -1, 0) - _shift(points, 1, 0)
    normal = np.cross(du, dv)
    norm = np.linalg.norm(normal, axis=-1) * np.linalg.norm(points, axis=-1)
    cos = np.abs(np.einsum("hwc,hwc->hw", normal, points)) / np.where(norm > 0, norm, 1.0)
    angle = np.arccos(np.clip(cos, 0.0, 1.0))
    missing = (depth <= 0) | (_shift(depth, 0, 1) <= 0) | (_shift(depth, 0, -1) <= 0) | \
        (_shift(depth, 1, 0) <= 0) | (_shift(depth, -1, 0) <= 0) | (norm == 0)
    return np.where(missing, np.pi / 2, angle)


def edges(depth: np.ndarray, jump: float, band: int) -> np.ndarray:
    """(H,W) bool: pixels within `band` pixels (along a row or column) of a depth step larger
    than `jump` times the nearer depth between 4-neighbours."""
    step = np.zeros(depth.shape, dtype=bool)
    for dv, du in ((0, 1), (1, 0)):
        other = _shift(depth, dv, du)
        near = np.minimum(depth, other)
        step |= np.abs(depth - other) > jump * np.where(near > 0, near, np.inf)
    grown = step.copy()
    for r in range(1, band + 1):  # within `band` pixels along a row or a column
        for dv, du in ((r, 0), (-r, 0), (0, r), (0, -r)):
            grown |= _shift(step, dv, du)
    return grown


def apply(depth: np.ndarray, rgb: np.ndarray, fx: float, fy: float, cx: float, cy: float, model: SensorModel,
          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(depth HxW float32 metres, 0 = missing; rgb HxWx3 uint8) as the sensor would give them,
    from the exact depth and colour of a frame whose pinhole intrinsics are fx, fy, cx, cy."""
    z = np.asarray(depth, dtype=np.float64)
    valid = z > 0
    theta = np.minimum(incidence(z, fx, fy, cx, cy), np.radians(89.0))
    zs = np.where(valid, z, 1.0)
    sigma = (model.axial_sigma_m + model.axial_sigma_per_m2 * (zs - 0.4) ** 2
             + 1e-4 / np.sqrt(zs) * theta**2 / (np.pi / 2 - theta) ** 2)
    noisy = np.maximum(zs + sigma * rng.standard_normal(z.shape), 0.05)
    fb = model.focal_px * model.baseline_m
    disparity = np.maximum(np.round(fb / noisy / model.disparity_step_px), 1.0) * model.disparity_step_px
    out = fb / disparity
    grey = rgb.astype(np.float64).mean(axis=2) / 255.0
    dark = rng.random(z.shape) < np.clip(1.0 - grey / model.dark_level, 0.0, 1.0) if model.dark_level > 0 else False
    lost = ~valid | edges(z, model.edge_jump, model.edge_band_px) | (theta > np.radians(model.max_incidence_deg)) | dark
    colour = np.clip(np.round(rgb + model.colour_sigma * rng.standard_normal(rgb.shape)), 0, 255).astype(np.uint8)
    return np.where(lost, 0.0, out).astype(np.float32), colour
