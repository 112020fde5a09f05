"""Where the map already explains a keyframe's view: the tests a strategy's `admit` uses to leave
out new Gaussians the map does not need (`StrategyConfig.skip_covered`).

Two tests, both on the keyframe's image plane, both with a depth tolerance (metres) so that a
surface in front of or behind the map is not taken for the map:

- `covered_by_render`: the map rendered from the keyframe is opaque at the point's pixel and
  its expected depth agrees. It needs a trained map: untrained Gaussians are faint (3DGS starts
  them at opacity 0.1), so a view is "covered" only after training made them opaque.
- `occupied_by_centres`: some map Gaussian's centre projects into the point's image cell
  (`cell` x `cell` pixels around a pixel of the keyframe's sampling grid) at a camera depth
  within the tolerance of the point's. It reads only
  the map's means (no render, no training needed), so a map that admits no point whose cell is
  occupied holds at most `min_centres` Gaussians (1 by default) per cell and depth of any view of
  the scene: its size is bounded by the scene's surface, not by how often the camera sees it.
"""

from __future__ import annotations

import torch

from slamkit.geometry.transforms import project_points
from slamkit.map.rendering import RenderOutput
from slamkit.types import Camera


def covered_by_render(points: torch.Tensor, render: RenderOutput, world_to_camera: torch.Tensor, camera: Camera,
                      min_alpha: float, depth_tolerance: float) -> torch.Tensor:
    """(N,) bool: the world points (N,3, metres) whose pixel in `render` (made with
    `world_to_camera` and `camera`) is covered: alpha > min_alpha and an expected depth (depth /
    alpha) within depth_tolerance metres of the point's camera depth. Points behind the camera
    or outside the image are not covered."""
    w2c = world_to_camera.to(device=points.device, dtype=torch.float32)
    u, v, z = project_points(points.float(), w2c, camera)
    u, v = torch.round(u).long(), torch.round(v).long()
    inside = (z > 1e-6) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    covered = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    ui, vi = u[inside], v[inside]
    alpha = render.alpha[vi, ui]
    depth = render.depth[vi, ui] / alpha.clamp_min(1e-6)
    covered[inside] = (alpha > min_alpha) & ((depth - z[inside]).abs() < depth_tolerance)
    return covered


def image_cells(points: torch.Tensor, world_to_camera: torch.Tensor, camera: Camera,
                cell: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(cell index (N,) int64, camera depth (N,) float64 metres, inside (N,) bool) of world
    points (N,3, metres). Cell (i, j) is the `cell` x `cell` pixel square centred on pixel
    (column i cell, row j cell), as a keyframe's Gaussians are sampled (every stride-th pixel
    from pixel 0: `slamkit.geometry.transforms.pixel_grid`), so a sample sits in the middle of
    its cell; cells are numbered row by row from the top-left. `inside` is False behind the
    camera or outside the image (their index is meaningless)."""
    w2c = world_to_camera.to(device=points.device, dtype=torch.float64)
    u, v, z = project_points(points.double(), w2c, camera)
    inside = (z > 1e-6) & (u > -0.5) & (u < camera.width - 0.5) & (v > -0.5) & (v < camera.height - 0.5)
    columns = int(camera.width / cell) + 2
    col = torch.floor(u.clamp(-0.5, camera.width) / cell + 0.5).long().clamp_min(0)
    row = torch.floor(v.clamp(-0.5, camera.height) / cell + 0.5).long().clamp_min(0)
    return row * columns + col, z, inside


def occupied_by_centres(points: torch.Tensor, centres: torch.Tensor, world_to_camera: torch.Tensor, camera: Camera,
                        cell: float, depth_tolerance: float, min_centres: int = 1) -> torch.Tensor:
    """(N,) bool: the world points (N,3, metres) whose image cell (`cell` x `cell` pixels of
    `camera`, seen through `world_to_camera`) holds the centres of at least `min_centres` of
    `centres` (M,3, the map's means) at camera depths within depth_tolerance metres of the
    point's own. Points behind the camera or outside the image are not occupied."""
    occupied = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    if len(points) == 0 or len(centres) == 0:
        return occupied
    map_cell, map_z, map_inside = image_cells(centres.detach().to(points.device), world_to_camera, camera, cell)
    new_cell, new_z, new_inside = image_cells(points, world_to_camera, camera, cell)
    map_cell, map_z = map_cell[map_inside], map_z[map_inside]
    if len(map_cell) == 0 or not bool(new_inside.any()):
        return occupied
    # one sorted key per centre, cell first and depth second, cells `span` apart (more than the
    # points' depths plus twice the tolerance; centres farther than that can never count, so
    # they are brought to that depth and a far-off centre cannot eat the keys' precision): the
    # centres of a point's cell within its depth tolerance are the keys strictly between its own
    # key -/+ the tolerance
    reach = float(new_z[new_inside].max()) + 2.0 * depth_tolerance
    map_z = map_z.clamp_max(reach)
    span = reach + 1.0
    keys = torch.sort(map_cell.double() * span + map_z).values
    key = new_cell[new_inside].double() * span + new_z[new_inside]
    first = torch.searchsorted(keys, key - depth_tolerance, side="right")
    past = torch.searchsorted(keys, key + depth_tolerance, side="left")
    occupied[new_inside] = past - first >= min_centres
    return occupied
