"""The viewer role: shows or records a run as it happens (optional: `viewer=none`)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from slamkit.config import PluginConfig, require
from slamkit.geometry.transforms import covariance_from_scales
from slamkit.map.gaussian_map import GaussianMap
from slamkit.roles.mapping import Mapper
from slamkit.roles.rendering import RenderOutput
from slamkit.types import Camera, Frame, KeyframeKind


@dataclass
class ViewerConfig(PluginConfig):
    """Options every viewer takes (a viewer's config may derive from this one)."""

    #: frames between renders of the map from the current pose (0: never; a render costs about a mapping step)
    render_every: int = 10
    #: resolution of those renders relative to the frame's, in (0, 1]
    render_scale: float = 0.5
    #: frames between logs of the Gaussian centres (0: only after the last frame)
    map_every: int = 10
    #: at most this many Gaussian centres a log (an even subsample of the map)
    map_max_points: int = 200_000

    def validate(self) -> None:
        require(self.render_every >= 0, "viewer.render_every", "an integer >= 0 (0 = never)", self.render_every)
        require(0 < self.render_scale <= 1, "viewer.render_scale", "in (0, 1]", self.render_scale)
        require(self.map_every >= 0, "viewer.map_every", "an integer >= 0 (0 = at the end only)", self.map_every)
        require(self.map_max_points >= 1, "viewer.map_max_points", "an integer >= 1", self.map_max_points)


@dataclass
class MapPoints:
    """Gaussian centres for display: positions (N,3) float32 world metres, colors (N,3) uint8
    RGB, radii (N,) float32 metres (the geometric mean of each Gaussian's standard deviations),
    out of `total` Gaussians in the map."""

    positions: np.ndarray
    colors: np.ndarray
    radii: np.ndarray
    total: int


@dataclass
class MapGaussians:
    """Gaussians for display as splats, in their natural form (not the optimiser's):
    means (N,3) float32 world metres; quats (N,4) float32 unit quaternions (w, x, y, z),
    world-from-Gaussian rotation; scales (N,3) float32 standard deviations in metres along the
    Gaussian's axes; opacities (N,) float32 in (0, 1); colors (N,3) float32 RGB in [0, 1]; out
    of `total` Gaussians in the map."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    total: int

    def __len__(self) -> int:
        return len(self.means)

    def covariances(self) -> np.ndarray:
        """(N,3,3) float32 world-frame covariances R diag(s^2) R^T in m^2."""
        return covariance_from_scales(self.quats.astype(np.float64), self.scales.astype(np.float64)).astype(np.float32)


@dataclass
class ViewerFrame:
    """What a viewer sees of one processed frame.

    frame: the input (rgb, depth in metres, camera, gt_pose camera-to-world or None). pose:
    the estimated camera-to-world pose (4x4, metres, OpenCV axes). keyframe, lost: the
    tracker's and keyframe policy's outcome. trajectory, gt_trajectory: (n,3) camera centres
    in world metres of the frames so far (gt: the frames that have ground truth; the estimate
    as corrected by the loop closure so far). keyframes: (K,3) the keyframes' camera centres so
    far, likewise. loops: (L,2,3) the loop closure's accepted loops, each the two keyframes'
    camera centres in world metres (earlier keyframe first). The map and
    the mapper are shared with the running SLAM: use `map_gaussians`, `map_points` and `render`, which copy
    under the map's lock.
    """

    frame: Frame
    pose: np.ndarray
    keyframe: KeyframeKind
    lost: bool
    trajectory: np.ndarray
    gt_trajectory: np.ndarray
    gaussian_map: GaussianMap
    mapper: Mapper
    keyframes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    loops: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))

    def map_gaussians(self, max_points: int) -> MapGaussians:
        """An even subsample (every k-th row) of at most `max_points` Gaussians, copied under
        the map's lock."""
        gm = self.gaussian_map
        with gm.lock:
            total = len(gm)
            step = max(1, -(-total // max_points))
            columns = (gm.means.detach()[::step], torch.nn.functional.normalize(gm.quats.detach()[::step], dim=1),
                       gm.scales.detach()[::step], gm.opacities.detach()[::step],
                       gm.colors.detach()[::step].clamp(0, 1))
            means, quats, scales, opacities, colors = (c.float().cpu().numpy().copy() for c in columns)
        return MapGaussians(means, quats, scales, opacities, colors, total)

    def map_points(self, max_points: int) -> MapPoints:
        """An even subsample (every k-th row) of at most `max_points` Gaussian centres."""
        g = self.map_gaussians(max_points)
        radii = np.exp(np.log(g.scales).mean(axis=1)).astype(np.float32) if len(g) else np.zeros(0, np.float32)
        return MapPoints(g.means, (g.colors * 255 + 0.5).astype(np.uint8), radii, g.total)

    def render(self, scale: float = 1.0) -> RenderOutput | None:
        """The mapper's render from the estimated pose at `scale` of the frame's resolution,
        or None when the mapper cannot render."""
        camera = self.frame.camera if scale == 1.0 else self.frame.camera.scaled(scale)
        return self.mapper.render_view(self.pose, camera)


class Viewer(ABC):
    """Shows (or records) a run as it happens. Optional: `viewer=none` does nothing.

    slamkit calls `start` once before the first frame, `show` after every processed frame
    (in the tracking thread; keep it cheap, do expensive things every n-th frame) and `close`
    once at the end, also when the run stops early. An exception from any of them is reported
    as a warning and the viewer is switched off: a viewer never stops a run.
    """

    def start(self, camera: Camera, out_dir: Path) -> None:
        """Called before the first frame with the dataset's camera (pixels) and the run folder."""

    @abstractmethod
    def show(self, view: ViewerFrame) -> None:
        """Log one processed frame."""

    def close(self, view: ViewerFrame | None) -> None:
        """Called after the last frame with its view (None if no frame was processed)."""

