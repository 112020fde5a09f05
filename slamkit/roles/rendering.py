"""The rasteriser role: render Gaussians to colour, depth and alpha, differentiably.

Backends (plugins) implement `Rasterizer.render`. `mapper/rasterizer=NAME` selects one for the
mapper (a mapper part), or `auto`: gsplat when CUDA is available, else the compiled CPU backend, else the
pure-PyTorch reference (`torch`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import torch

from slamkit.geometry.transforms import invert_pose
from slamkit.map.gaussian_map import GaussianMap
from slamkit.types import Camera


@dataclass
class RenderOutput:
    """color (H,W,3) in [0,1] over the background; depth (H,W) metres, the alpha-weighted
    camera z (sum_i w_i z_i, not normalised by alpha); alpha (H,W) accumulated opacity."""

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor

    def expected_depth(self, min_alpha: float = 0.5) -> torch.Tensor:
        """(H,W) metres: depth / alpha where alpha >= min_alpha (the surface the pixel sees),
        0 elsewhere (too transparent to trust)."""
        solid = self.alpha >= min_alpha
        return torch.where(solid, self.depth / self.alpha.clamp_min(1e-6), torch.zeros_like(self.depth))

    def expected_color(self, min_alpha: float = 0.5) -> torch.Tensor:
        """(H,W,3) in [0,1]: colour / alpha (the Gaussians' colour without the black background)
        where alpha >= min_alpha, 0 elsewhere."""
        solid = (self.alpha >= min_alpha)[..., None]
        color = (self.color / self.alpha.clamp_min(1e-6)[..., None]).clamp(0, 1)
        return torch.where(solid, color, torch.zeros_like(color))


class Rasterizer(ABC):
    """Differentiable 3DGS rasterisation for a pinhole camera (principal point honoured).

    Conventions shared by every backend so that they agree to float precision:
    - EWA 2D covariance J W Sigma W^T J^T + 0.3 px^2 I, x/z and y/z in J clamped to the image
      plus 15 % on each side (as 3DGS and gsplat); camera z <= 0.01 m is culled;
    - a Gaussian covers exactly the pixels where its alpha >= 1/255 (no 3-sigma box); pixel
      centres at integer coordinates (u, v) = (column, row), as in the intrinsics;
    - per pixel, front to back by camera z, alpha_i = min(0.99, o_i exp(-q/2)) (gsplat's 0.999:
      the backends agree where opacity <= 0.99); compositing stops before a Gaussian that would
      bring the transmittance below 1e-4;
    - colour = sum_i w_i c_i + (1 - alpha) background, w_i = alpha_i T_i.
    Outputs are on the inputs' device, gradients flow back to it, whatever device a backend uses.
    """

    @abstractmethod
    def render(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        world_to_camera: torch.Tensor,
        camera: Camera,
        background: torch.Tensor | None = None,
    ) -> RenderOutput:
        """means (N,3) world metres; quats (N,4) (w,x,y,z), normalised inside; scales (N,3)
        metres (standard deviations); opacities (N,) in [0,1]; colors (N,3); world_to_camera
        (4,4) (the inverse of the camera-to-world pose); background (3,) or None for black.
        Gradients flow to means, quats, scales, opacities and colors."""


def render_map(rasterizer: Rasterizer, gaussian_map: GaussianMap, pose: np.ndarray, camera: Camera) -> RenderOutput:
    """Render the whole map from `pose` (4x4 camera-to-world, metres, OpenCV axes) with
    `camera`, without gradients, under the map's lock (safe beside a mapping thread). An empty
    map renders black with zero depth and alpha."""
    world_to_camera = torch.as_tensor(invert_pose(np.asarray(pose, dtype=np.float64)), dtype=torch.float32,
                                      device=gaussian_map.device)
    with gaussian_map.lock, torch.no_grad():
        if len(gaussian_map) == 0:
            zeros = torch.zeros((camera.height, camera.width), device=gaussian_map.device)
            color = torch.zeros((camera.height, camera.width, 3), device=zeros.device)
            return RenderOutput(color, zeros, zeros.clone())
        out = rasterizer.render(
            gaussian_map.means.detach(),
            gaussian_map.quats.detach(),
            gaussian_map.scales.detach(),
            gaussian_map.opacities.detach(),
            gaussian_map.colors.detach(),
            world_to_camera,
            camera,
        )
    return RenderOutput(out.color.detach(), out.depth.detach(), out.alpha.detach())

