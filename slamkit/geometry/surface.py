"""Does the map seen from a pose lie on a frame's observed surface? The check from the map's side:
an alignment counts the frame's points that lie near the map, this counts the map's surface in
view that lies on the frame's depth. A frame placed wrongly sees map centres in front of its
surface (it would see through them) or behind it; a frame placed rightly that sees new surface
beyond the map matches fewer of its points but still agrees wherever the map is in view."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamkit.geometry.transforms import invert_pose, project_points

#: A centre lies on the observed surface when its camera depth differs from the depth observed at
#: its pixel by at most SURFACE_TOLERANCE_M metres plus SURFACE_TOLERANCE_REL of that depth (a
#: Kinect's depth error grows with the range).
SURFACE_TOLERANCE_M, SURFACE_TOLERANCE_REL = 0.05, 0.02
#: Image cells (pixels a side) in which only the map's nearest centre is compared with the frame:
#: centres hidden behind it do not count against a pose.
SURFACE_CELL_PX = 8


@dataclass(frozen=True)
class SurfaceCells:
    """One entry per image cell holding a map centre on valid depth: `index` of the cell's nearest
    centre (into the centres given), its pixel (`row`, `col`), and whether it lies on the observed
    surface (`on`)."""

    index: np.ndarray
    row: np.ndarray
    col: np.ndarray
    on: np.ndarray

    @property
    def agreement(self) -> float | None:
        """The fraction of the cells whose nearest centre lies on the surface (None: no cell)."""
        return float(self.on.mean()) if len(self.on) else None


def surface_cells(centres: np.ndarray, depth: np.ndarray, camera, camera_to_world: np.ndarray) -> SurfaceCells:
    """`SurfaceCells` of the map's `centres` ((N,3) world, metres) seen from `camera_to_world`
    (4x4) by `camera` in a frame of observed `depth` ((H,W) metres; <= 0 or not finite: none).
    Depth beyond a frame's `depth_trunc` counts too: a centre in front of a far wall is as wrong."""
    u, v, z = project_points(np.asarray(centres, dtype=np.float64), invert_pose(np.asarray(camera_to_world,
                                                                                        dtype=np.float64)), camera)
    col, row = np.rint(u), np.rint(v)
    inside = (z > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    index = np.flatnonzero(inside)
    col, row, z = col[inside].astype(np.int64), row[inside].astype(np.int64), z[inside]
    observed = np.asarray(depth, dtype=np.float32)[row, col]
    seen = np.isfinite(observed) & (observed > 0)
    index, col, row, z, observed = index[seen], col[seen], row[seen], z[seen], observed[seen]
    cell = (row // SURFACE_CELL_PX) * (camera.width // SURFACE_CELL_PX + 1) + col // SURFACE_CELL_PX
    order = np.lexsort((z, cell))  # by cell, then nearest first
    nearest = order[np.r_[True, cell[order][1:] != cell[order][:-1]]] if len(order) else order
    on = np.abs(z[nearest] - observed[nearest]) <= SURFACE_TOLERANCE_M + SURFACE_TOLERANCE_REL * observed[nearest]
    return SurfaceCells(index=index[nearest], row=row[nearest], col=col[nearest], on=on)
