"""The synthetic scene: a furnished 6 x 5 x 3 m room seen from inside, as primitives (built once).

A sofa, a table, a cabinet, a bookshelf, a floor lamp, a stool, balls, a rug, a door, a window,
pictures, a clock, a ceiling beam and lamp; every surface has its own material. World frame:
metres, z up, the floor at z = 0, the room spans x in [-3, 3], y in [-2.5, 2.5]. The order of the
primitives matters: where two are hit at the same distance, the renderer keeps the first.
"""

from __future__ import annotations

import threading

import numpy as np

from slamkit_plugins.datasets.synthetic.materials import (
    mat_angle_stripes,
    mat_beach_ball,
    mat_book,
    mat_ceiling,
    mat_checker,
    mat_clock,
    mat_floor,
    mat_noise,
    mat_painting,
    mat_poster,
    mat_radiator,
    mat_rings,
    mat_rug,
    mat_solid,
    mat_wall_east,
    mat_wall_north,
    mat_wall_south,
    mat_wall_west,
    mat_window,
    mat_wood,
)
from slamkit_plugins.datasets.synthetic.primitives import Primitive, box, cylinder, rotation_deg, sphere

#: The room: x in [-3, 3], y in [-2.5, 2.5], z in [0, 3] metres.
ROOM_LO = np.array([-3.0, -2.5, 0.0])
ROOM_HI = np.array([3.0, 2.5, 3.0])

#: Dark metal: the table's legs and the floor lamp.
_METAL = mat_solid((0.18, 0.18, 0.20), 0.1, 0.1)

_SCENE: list[Primitive] | None = None
_SCENE_LOCK = threading.Lock()


def scene() -> list[Primitive]:
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


def _build_scene() -> list[Primitive]:
    """The room's faces, the furniture, then what is on the walls and the ceiling, in that order."""
    return _room() + _sofa() + _table() + _cabinet() + _bookshelf() + _floor_objects() + _wall_objects()


def _room() -> list[Primitive]:
    """The room's six faces, seen from inside (planes with inward normals)."""
    P: list[Primitive] = []
    walls = [
        ("west wall", mat_wall_west),
        ("east wall", mat_wall_east),
        ("south wall", mat_wall_south),
        ("north wall", mat_wall_north),
        ("floor", mat_floor),
        ("ceiling", mat_ceiling),
    ]
    for k, (name, mat) in enumerate(walls):
        axis, high = divmod(k, 2)
        point = (ROOM_LO + ROOM_HI) / 2
        point[axis] = ROOM_HI[axis] if high else ROOM_LO[axis]
        normal = np.zeros(3)
        normal[axis] = -1.0 if high else 1.0
        P.append(Primitive("plane", point, normal, np.eye(3), mat, name))
    return P


def _sofa() -> list[Primitive]:
    """Sofa against the south wall, with two cushions."""
    P: list[Primitive] = []
    fabric = mat_noise((0.45, 0.08, 0.10), (0.75, 0.22, 0.20), 0.12, 2, 1.4)
    P.append(box((-1.95, -2.26, 0.0), (-0.05, -1.60, 0.42), fabric, "sofa seat"))
    P.append(box((-2.15, -2.50, 0.0), (0.15, -2.26, 0.92), fabric, "sofa back"))
    P.append(box((-2.15, -2.26, 0.0), (-1.95, -1.55, 0.62), fabric, "sofa arm"))
    P.append(box((-0.05, -2.26, 0.0), (0.15, -1.55, 0.62), fabric, "sofa arm"))
    P.append(
        box(
            (-1.80, -2.22, 0.42),
            (-1.35, -2.06, 0.80),
            mat_checker((0.95, 0.75, 0.15), (0.35, 0.20, 0.05), 0.06),
            "cushion",
            rotation_deg(8, 0, 12),
            np.array([-1.57, -2.14, 0.42]),
        )
    )
    P.append(
        box(
            (-0.75, -2.22, 0.42),
            (-0.30, -2.06, 0.78),
            mat_rings((0.2, 0.55, 0.65), (0.9, 0.9, 0.85), 0.05),
            "cushion",
            rotation_deg(-10, 0, 10),
            np.array([-0.52, -2.14, 0.42]),
        )
    )
    return P


def _table() -> list[Primitive]:
    """Table (rotated 15 deg) with legs, a ball, a mug and a book on it, east side."""
    P: list[Primitive] = []
    Rt, piv = rotation_deg(15), np.array([1.95, 0.55, 0.0])
    wood = mat_wood((0.45, 0.28, 0.14), (0.70, 0.48, 0.28), 0)
    P.append(box((1.35, 0.15, 0.72), (2.55, 0.95, 0.77), wood, "table top", Rt, piv))
    for lx in (1.40, 2.45):
        for ly in (0.20, 0.85):
            P.append(box((lx, ly, 0.0), (lx + 0.05, ly + 0.05, 0.72), _METAL, "table leg", Rt, piv))
    P.append(
        sphere(
            Rt @ (np.array([2.25, 0.40, 0.0]) - piv) + piv + (0, 0, 0.89),
            0.12,
            mat_checker((0.05, 0.05, 0.05), (0.95, 0.95, 0.95), 0.04),
            "ball",
        )
    )
    P.append(
        cylinder(
            Rt @ (np.array([1.65, 0.75, 0.0]) - piv) + piv + (0, 0, 0.83),
            0.045,
            0.06,
            mat_rings((0.8, 0.1, 0.1), (0.95, 0.95, 0.95), 0.03),
            "mug",
        )
    )
    P.append(box((1.55, 0.30, 0.77), (1.85, 0.52, 0.82), mat_solid((0.1, 0.45, 0.2)), "book", Rt @ rotation_deg(20),
                 piv))
    return P


def _cabinet() -> list[Primitive]:
    """Cabinet in the north-west corner: drawers, handles, a vase on top."""
    P: list[Primitive] = []
    P.append(
        box(
            (-3.0, 1.35, 0.0), (-2.25, 2.5, 1.2), mat_checker((0.85, 0.85, 0.82), (0.70, 0.72, 0.75), 0.15), "cabinet"
        )
    )
    for z0 in (0.08, 0.46, 0.84):
        P.append(box((-2.25, 1.42, z0), (-2.22, 2.43, z0 + 0.32), mat_solid((0.15, 0.45, 0.50), 0.12, 0.2), "drawer"))
        P.append(box((-2.22, 1.80, z0 + 0.14), (-2.19, 2.05, z0 + 0.18), mat_solid((0.8, 0.7, 0.3), 0.05), "handle"))
    P.append(
        cylinder((-2.62, 1.92, 1.38), 0.10, 0.18, mat_rings((0.15, 0.25, 0.70), (0.90, 0.90, 0.95), 0.06), "vase")
    )
    return P


def _bookshelf() -> list[Primitive]:
    """Bookshelf against the north wall: sides, boards, books of varied sizes, a globe."""
    P: list[Primitive] = []
    dark = mat_wood((0.25, 0.15, 0.08), (0.40, 0.26, 0.14), 0, 0.03)
    P.append(box((0.20, 2.15, 0.0), (0.24, 2.5, 1.9), dark, "shelf side"))
    P.append(box((1.76, 2.15, 0.0), (1.80, 2.5, 1.9), dark, "shelf side"))
    for z in (0.0, 0.5, 1.0, 1.45, 1.86):
        P.append(box((0.24, 2.15, z), (1.76, 2.5, z + 0.04), dark, "shelf board"))
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
                P.append(box((x, 2.48 - dep, z), (x + w, 2.48, z + hgt), mat_book(nb, hgt / 2), "book"))
                nb += 1
            x += w + rng.uniform(0.0, 0.03)
    P.append(sphere((1.2, 2.33, 1.49 + 0.11), 0.11, mat_noise((0.1, 0.5, 0.3), (0.8, 0.9, 0.3), 0.05, 2), "globe"))
    return P


def _floor_objects() -> list[Primitive]:
    """Floor lamp in the south-east corner, a stool, a big beach ball, a rug."""
    P: list[Primitive] = []
    P.append(cylinder((2.45, -1.95, 0.015), 0.18, 0.015, _METAL, "lamp base"))
    P.append(cylinder((2.45, -1.95, 0.76), 0.022, 0.73, _METAL, "lamp pole"))
    P.append(
        cylinder(
            (2.45, -1.95, 1.62),
            0.20,
            0.15,
            mat_angle_stripes((0.95, 0.90, 0.75), (0.80, 0.65, 0.45), 12),
            "lamp shade",
        )
    )
    P.append(
        cylinder(
            (1.10, -1.25, 0.23), 0.20, 0.23, mat_angle_stripes((0.95, 0.55, 0.10), (0.25, 0.15, 0.60), 8), "stool"
        )
    )
    P.append(sphere((-0.95, 1.15, 0.30), 0.30, mat_beach_ball, "beach ball"))
    P.append(box((-1.3, -1.1, 0.0), (0.7, 0.6, 0.012), mat_rug, "rug"))
    return P


def _wall_objects() -> list[Primitive]:
    """On the walls: painting and radiator (west), poster and door (east), window (south),
    clock (north); a beam and a lamp on the ceiling."""
    P: list[Primitive] = []
    P.append(box((-3.0, -0.65, 1.15), (-2.96, 0.65, 2.05), mat_solid((0.3, 0.2, 0.1), 0.05), "picture frame"))
    P.append(box((-2.96, -0.58, 1.22), (-2.95, 0.58, 1.98), mat_painting, "painting"))
    P.append(box((-3.0, -0.8, 0.15), (-2.9, 0.8, 0.70), mat_radiator, "radiator"))
    P.append(box((2.99, -1.55, 1.0), (3.0, -0.55, 2.0), mat_poster, "poster"))
    P.append(
        box((2.95, 0.95, 0.0), (3.0, 1.95, 2.1), mat_wood((0.55, 0.36, 0.20), (0.75, 0.55, 0.35), 2, 0.05), "door")
    )
    P.append(sphere((2.91, 1.80, 1.0), 0.035, mat_solid((0.85, 0.75, 0.35), 0.03), "door knob"))
    P.append(box((-1.6, -2.5, 1.25), (-0.4, -2.47, 2.15), mat_window, "window"))
    P.append(box((-1.68, -2.5, 1.19), (-0.32, -2.38, 1.25), mat_solid((0.95, 0.95, 0.93), 0.05), "window sill"))
    P.append(cylinder((-1.0, 2.47, 2.05), 0.2, 0.03, mat_clock, "clock", rotation_deg(0, 0, 90)))
    P.append(
        box((-1.65, -2.5, 2.8), (-1.4, 2.5, 3.0), mat_wood((0.50, 0.32, 0.18), (0.68, 0.46, 0.26), 1, 0.05), "beam")
    )
    P.append(sphere((0.6, 0.2, 2.78), 0.17, mat_solid((1.0, 0.97, 0.85), 0.02), "ceiling lamp"))
    return P
