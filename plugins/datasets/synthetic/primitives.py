"""Primitives of the synthetic scene and their ray tests, in metres.

A primitive is a plane, box, sphere or cylinder in its own local frame (centre in world
coordinates, rotation R local -> world); its ray test takes the ray origin and directions in
that local frame and returns the hit distance t (inf on a miss), in units of the direction
vectors' length. `Hit` is what a material sees of the pixels that hit a primitive, `Material`
the function that colours them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

_EPS = 1e-6


def rotation_deg(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in degrees."""
    a, b, c = np.radians([yaw, pitch, roll])
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    return rz @ ry @ rx


@dataclass
class Hit:
    """The n pixels whose nearest hit is one primitive."""

    p: np.ndarray  # (n, 3) world points
    pl: np.ndarray  # (n, 3) points in the primitive's local frame
    nl: np.ndarray  # (n, 3) local normals
    face: np.ndarray  # (n,) int: box faces 2*axis + (normal > 0); cylinders 4 / 5 caps, 6 side
    fw: np.ndarray  # (n,) pixel footprint in metres


#: A material maps a hit to colours: f(hit) -> (n, 3) float32 RGB in [0, 1], before shading.
Material = Callable[[Hit], np.ndarray]


@dataclass
class Primitive:
    """A plane, box, sphere or cylinder placed in the world, with its material and a name."""

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


def box(lo, hi, material, name="", R=None, pivot=None) -> Primitive:
    """Axis-aligned box from corners lo..hi; optionally rotated by R about `pivot` (world)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, s = (lo + hi) / 2, (hi - lo) / 2
    R = np.eye(3) if R is None else R
    if pivot is not None:
        c = R @ (c - pivot) + pivot
    return Primitive("box", c, s, R, material, name)


def sphere(c, r, material, name="") -> Primitive:
    """Sphere of radius r (m) centred at c (world)."""
    return Primitive("sphere", np.asarray(c, float), np.full(3, float(r)), np.eye(3), material, name)


def cylinder(c, r, half_h, material, name="", R=None) -> Primitive:
    """Cylinder of radius r and half height half_h (m) along its local z axis, centred at c (world);
    R: local -> world (default identity)."""
    return Primitive(
        "cylinder", np.asarray(c, float), np.array([r, r, half_h], float), np.eye(3) if R is None else R, material, name
    )
