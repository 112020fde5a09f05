"""Where the map already explains a keyframe's view: the tests a strategy's `admit` uses to leave
out new Gaussians the map does not need (`StrategyConfig.skip_covered`).

Two tests, both on the keyframe's image plane, both with a depth tolerance (metres, growing
with the square of the depth: `depth_tolerances`) so that a surface in front of or behind the
map is not taken for the map:

- `covered_by_render`: the map rendered from the keyframe is opaque at the point's pixel and
  its expected depth agrees. It needs a trained map: untrained Gaussians are faint (3DGS starts
  them at opacity 0.1), so a view is "covered" only after training made them opaque.
- `occupied_by_centres`: some map Gaussian's centre projects near the point's pixel (within
  cell / sqrt(2) pixels, `cell` being the keyframe's sampling stride) at a camera depth within
  the tolerance of the point's. It reads only the map's means (no render, no training needed),
  so a map that admits no occupied point holds about `min_centres` Gaussians (1 by default) per
  cell and depth of any view of the scene: its size is bounded by the scene's surface, not by
  how often the camera sees it. The disc, not the square cell of earlier versions, makes the
  test indifferent to how a view is rotated against the keyframes that built the map: the
  square left ~3 % of a revisited view's cells empty where the map's grid of centres, seen at
  another angle, skipped them, and each revisit added Gaussians there (docs/results.md).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from slamkit.geometry.transforms import project_points
from slamkit.map.rendering import RenderOutput
from slamkit.types import Camera


def covered_by_render(points: torch.Tensor, render: RenderOutput, world_to_camera: torch.Tensor, camera: Camera,
                      min_alpha: float, depth_tolerance: float, depth_quadratic: float = 0.0) -> torch.Tensor:
    """(N,) bool: the world points (N,3, metres) whose pixel in `render` (made with
    `world_to_camera` and `camera`) is covered: alpha > min_alpha and an expected depth (depth /
    alpha) within `depth_tolerances` of the point's camera depth. Points behind the camera or
    outside the image are not covered."""
    w2c = world_to_camera.to(device=points.device, dtype=torch.float32)
    u, v, z = project_points(points.float(), w2c, camera)
    u, v = torch.round(u).long(), torch.round(v).long()
    inside = (z > 1e-6) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    covered = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    ui, vi = u[inside], v[inside]
    alpha = render.alpha[vi, ui]
    depth = render.depth[vi, ui] / alpha.clamp_min(1e-6)
    zi = z[inside]
    covered[inside] = (alpha > min_alpha) & ((depth - zi).abs() < depth_tolerances(zi, depth_tolerance, depth_quadratic))
    return covered


def depth_tolerances(z: torch.Tensor, tolerance: float, quadratic: float) -> torch.Tensor:
    """Metres: how far a depth may be from camera depth z (metres) and still be the same
    surface, max(tolerance, quadratic z^2) (a structured-light sensor's depth error grows with the
    square of the range: Kinect v1 ~4 cm quantisation at 3.7 m)."""
    return torch.clamp_min(quadratic * z * z, tolerance)


def depth_coordinate(z: torch.Tensor, tolerance: float, quadratic: float) -> torch.Tensor:
    """A monotone function of camera depth z (metres) with slope 1 / depth_tolerances(z): two
    depths less than 1 apart in it differ by less than the tolerance at some depth between them."""
    if quadratic <= 0:
        return z / tolerance
    z0 = math.sqrt(tolerance / quadratic)  # where the quadratic term takes over
    return torch.where(z <= z0, z / tolerance, z0 / tolerance + (1.0 / z0 - 1.0 / z.clamp_min(z0)) / quadratic)


def occupied_by_centres(points: torch.Tensor, centres: torch.Tensor, world_to_camera: torch.Tensor, camera: Camera,
                        cell: float, depth_tolerance: float, min_centres: int = 1,
                        depth_quadratic: float = 0.0) -> torch.Tensor:
    """(N,) bool: the world points (N,3, metres) near which, seen through `world_to_camera` with
    `camera`, at least `min_centres` of `centres` (M,3, the map's means) project: within the
    disc of radius cell / sqrt(2) pixels around the point's pixel (the circle through the corners
    of its `cell` x `cell` square, so that any grid of centres spaced `cell` pixels apart, at any
    rotation, occupies every point) and at a camera depth within `depth_tolerances` of the
    point's. The two are combined as an ellipse, (pixel distance / radius)^2 + (depth difference
    in `depth_coordinate`)^2 < 1. Points behind the camera or outside the image are not
    occupied."""
    occupied = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    if len(points) == 0 or len(centres) == 0:
        return occupied
    radius = cell / math.sqrt(2.0)
    w2c = world_to_camera.detach().to(device="cpu", dtype=torch.float64)

    def scaled(world: torch.Tensor, margin: float) -> tuple[np.ndarray, np.ndarray]:
        u, v, z = project_points(world.detach().to(device="cpu", dtype=torch.float64), w2c, camera)
        inside = ((z > 1e-6) & (u > -0.5 - margin) & (u < camera.width - 0.5 + margin)
                  & (v > -0.5 - margin) & (v < camera.height - 0.5 + margin))
        coords = torch.stack([u / radius, v / radius, depth_coordinate(z, depth_tolerance, depth_quadratic)], dim=1)
        return coords[inside].numpy(), inside.numpy()

    map_coords, _ = scaled(centres, margin=radius)  # centres just outside the image occupy its border
    new_coords, new_inside = scaled(points, margin=0.0)
    if len(map_coords) < min_centres or not new_inside.any():
        return occupied
    from pykdtree.kdtree import KDTree

    dist, _ = KDTree(map_coords).query(new_coords, k=min_centres, distance_upper_bound=1.0)
    near = dist.reshape(len(new_coords), min_centres)[:, -1] < 1.0
    occupied[torch.from_numpy(new_inside).to(points.device)] = torch.from_numpy(near).to(points.device)
    return occupied
