"""Where the map already explains a keyframe's view: the tests `.admission` uses
to leave out new Gaussians the map does not need (`mapper.admission.skip_covered`).

Both tests are on the keyframe's image plane, with a depth tolerance (`DepthTolerance`) so that
a surface in front of or behind the map is not taken for the map:

- `covered_by_render`: the map rendered from the keyframe is opaque at the point's pixel and its
  expected depth agrees; it needs a trained map (untrained Gaussians are faint).
- `occupied_by_centres`: some map Gaussian's centre projects within cell / sqrt(2) pixels of the
  point's pixel at its depth (`cell`: the keyframe's sampling stride). It reads only the means, so
  a map that admits no occupied point holds about `min_centres` Gaussians per cell and depth of
  any view: its size is bounded by the scene's surface, not by how often the camera sees it (a
  disc, not a square: docs/results.md, "Bounded maps on loops").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from slamkit.geometry.transforms import project_points
from slamkit.roles.rendering import RenderOutput
from slamkit.types import Camera


@dataclass(frozen=True)
class DepthTolerance:
    """How far apart two camera depths may be and still be one surface: max(absolute,
    quadratic z^2) metres at camera depth z (metres); quadratic in 1/metres, 0 for a constant
    tolerance (a structured-light sensor's depth error grows with the square of the range)."""

    absolute: float
    quadratic: float = 0.0

    def at(self, z: torch.Tensor) -> torch.Tensor:
        """Metres, at camera depths z (metres)."""
        return torch.clamp_min(self.quadratic * z * z, self.absolute)

    def coordinate(self, z: torch.Tensor) -> torch.Tensor:
        """The integral of 1 / `at` over depth (from 0): a monotone function of camera depth z
        (metres) in which two depths less than 1 apart differ by less than the tolerance at some
        depth between them."""
        if self.quadratic <= 0:
            return z / self.absolute
        z0 = math.sqrt(self.absolute / self.quadratic)  # where the quadratic term takes over
        beyond = (1.0 / z0 - 1.0 / z.clamp_min(z0)) / self.quadratic
        return torch.where(z <= z0, z / self.absolute, z0 / self.absolute + beyond)


def covered_by_render(points: torch.Tensor, render: RenderOutput, world_to_camera: torch.Tensor, camera: Camera,
                      min_alpha: float, tolerance: DepthTolerance) -> torch.Tensor:
    """(N,) bool: the world points (N,3, metres) whose pixel in `render` (made with
    `world_to_camera` and `camera`) is covered: alpha > min_alpha and an expected depth (depth /
    alpha) within `tolerance` of the point's camera depth. Points behind the camera or outside
    the image are not covered."""
    w2c = world_to_camera.to(device=points.device, dtype=torch.float32)
    u, v, z = project_points(points.float(), w2c, camera)
    u, v = torch.round(u).long(), torch.round(v).long()
    inside = (z > 1e-6) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    covered = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    ui, vi = u[inside], v[inside]
    alpha = render.alpha[vi, ui]
    depth = render.depth[vi, ui] / alpha.clamp_min(1e-6)
    zi = z[inside]
    covered[inside] = (alpha > min_alpha) & ((depth - zi).abs() < tolerance.at(zi))
    return covered


def occupied_by_centres(points: torch.Tensor, centres: torch.Tensor, world_to_camera: torch.Tensor, camera: Camera,
                        cell: float, tolerance: DepthTolerance, min_centres: int = 1) -> torch.Tensor:
    """(N,) bool: the world points (N,3, metres) near which, seen through `world_to_camera` with
    `camera`, at least `min_centres` of `centres` (M,3, the map's means) project: inside the
    ellipse (pixel distance / r)^2 + (depth difference in `tolerance.coordinate`)^2 < 1, with r =
    cell / sqrt(2) pixels. At the point's own depth that is the disc through the corners of its
    `cell` x `cell` square, so that a grid of centres spaced `cell` pixels apart at that depth
    occupies every point at any rotation; a centre as far off in depth as the tolerance counts
    only at the point's pixel. Points behind the camera or outside the image are not occupied."""
    occupied = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    if len(points) == 0 or len(centres) == 0:
        return occupied
    radius = cell / math.sqrt(2.0)
    w2c = world_to_camera.detach().to(device=points.device, dtype=torch.float64)

    def ellipse_coordinates(world: torch.Tensor, margin: float) -> tuple[np.ndarray, torch.Tensor]:
        """((V,3) numpy (u / r, v / r, depth coordinate) of the visible points, (N,) bool which
        are visible): in front of the camera and within `margin` pixels of the image."""
        u, v, z = project_points(world.detach().to(device=points.device, dtype=torch.float64), w2c, camera)
        visible = ((z > 1e-6) & (u > -0.5 - margin) & (u < camera.width - 0.5 + margin)
                   & (v > -0.5 - margin) & (v < camera.height - 0.5 + margin))
        coords = torch.stack([u / radius, v / radius, tolerance.coordinate(z)], dim=1)[visible]
        return coords.cpu().numpy(), visible

    map_coords, _ = ellipse_coordinates(centres, margin=radius)  # centres just outside the image occupy its border
    new_coords, new_visible = ellipse_coordinates(points, margin=0.0)
    if len(map_coords) == 0 or len(new_coords) == 0:
        return occupied
    from pykdtree.kdtree import KDTree

    # missing neighbours come back at an infinite distance
    dist, _ = KDTree(map_coords).query(new_coords, k=min_centres, distance_upper_bound=1.0)
    near = dist.reshape(len(new_coords), min_centres)[:, -1] < 1.0
    occupied[new_visible] = torch.from_numpy(near).to(points.device)
    return occupied
