"""The map's surface agreement with a frame (`slamkit.geometry.surface`): of the image cells seeing
the map, the fraction whose nearest map centre lies on the frame's depth."""

from __future__ import annotations

import numpy as np

from slamkit.geometry.surface import surface_cells
from slamkit.geometry.transforms import backproject, make_pose
from slamkit.types import Camera

CAMERA = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def wall(depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A frame's depth of a wall `depth_m` metres ahead and the wall's points (a centre per pixel)."""
    depth = np.full((CAMERA.height, CAMERA.width), depth_m, np.float32)
    return depth, backproject(depth, CAMERA)[0].astype(np.float64)


def test_a_surface_the_map_holds_twice_counts_only_where_it_is_nearest():
    """The wall held twice, its second copy 0.3 m behind the first (drift): from the frame's pose
    the hidden copy does not count against it; from 0.3 m further back the frame's wall is the
    far copy and the near one stands in front of it in every cell; from 0.15 m nearer the whole
    map lies behind the surface it sees."""
    depth, near = wall(2.0)
    far = near * (2.3 / 2.0)
    centres = np.concatenate([near, far])
    assert surface_cells(centres, depth, CAMERA, np.eye(4)).agreement == 1.0
    back = make_pose(np.eye(3), np.array([0.0, 0.0, -0.3]))
    cells = surface_cells(centres, depth, CAMERA, back)
    assert cells.agreement == 0.0 and (cells.index < len(near)).all()  # each cell judged by its nearest centre
    forward = make_pose(np.eye(3), np.array([0.0, 0.0, 0.15]))
    assert surface_cells(centres, depth, CAMERA, forward).agreement == 0.0


def test_only_cells_with_observed_depth_and_a_centre_in_view_count():
    """Pixels without depth (0 or NaN) judge nothing: the left half of the frame blank, the map's
    centres there are not counted; a map wholly behind the camera gives no agreement (None)."""
    depth, centres = wall(2.0)
    depth[:, :32] = 0.0
    depth[:24, :32] = np.nan
    cells = surface_cells(centres, depth, CAMERA, np.eye(4))
    assert cells.agreement == 1.0 and (cells.col >= 32).all()
    assert len(cells.on) == (CAMERA.height // 8) * (CAMERA.width // 2 // 8)  # one per 8x8 cell of the right half
    turned = make_pose(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))  # facing away
    assert surface_cells(centres, depth, CAMERA, turned).agreement is None
