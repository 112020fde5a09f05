"""The rasteriser role: render Gaussians to colour, depth and alpha, differentiably.

Backends (plugins, hook `slamkit_rasterizers`) implement `Rasterizer.render`. `mapper.rasterizer`
names one, or `auto`: gsplat when CUDA is available, else the compiled CPU backend, else the
pure-PyTorch reference (`torch`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch

from slamkit.types import Camera


@dataclass
class RenderOutput:
    """color (H,W,3) in [0,1] over the background; depth (H,W) metres, the alpha-weighted
    camera z (sum_i w_i z_i, not normalised by alpha); alpha (H,W) accumulated opacity."""

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor


class Rasterizer(ABC):
    """Differentiable 3DGS rasterisation for a pinhole camera (principal point honoured).

    Conventions shared by every backend so that they agree to float precision:
    - projection of the mean, EWA 2D covariance J W Sigma W^T J^T plus 0.3 px^2 on the diagonal
      (the usual low-pass term), with x/z and y/z in the Jacobian clamped to the image plus 15%
      on each side (as 3DGS and gsplat); Gaussians with camera z <= 0.01 m are culled;
    - a Gaussian covers exactly the pixels where its alpha >= 1/255 (no 3-sigma box);
    - pixel centres at integer coordinates (u, v) = (column, row), as in the intrinsics;
    - per pixel, Gaussians sorted by camera z, front to back; alpha_i = min(0.99, o_i exp(-q/2));
      pairs with alpha_i < 1/255 are skipped (gsplat clamps at 0.999, not 0.99: the backends agree
      where opacity <= 0.99); compositing stops before a Gaussian that would
      bring the transmittance below 1e-4;
    - colour = sum_i w_i c_i + (1 - alpha) * background, w_i = alpha_i T_i.
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
