"""`loss=l1_ssim_depth`: GS-ICP SLAM's mapping loss (paper Eq. 9, as the reference code).

    loss = w_l1 L1(colour) + w_ssim (1 - SSIM(colour)) + w_depth L1(depth / 10 m)

over the pixels with valid observed depth (all pixels for the colour terms when none has
depth; no depth term then). L1 terms are means over those pixels (and the 3 channels); SSIM is
pytorch-msssim's (window 11, sigma 1.5) with the pixels outside the mask set to 0 in both
images (`slamkit.metrics.images.ssim`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from slamkit.metrics import images as image_metrics
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.map.rendering import RenderOutput
from slamkit.roles import MappingLoss, PluginConfig, TrainingView, require


@dataclass
class L1SSIMDepthConfig(PluginConfig):
    """weight_l1, weight_ssim, weight_depth: the loss's weights (reference: 0.8, 0.2, 0.1).
    depth_unit: metres; the depth term is L1(depth / depth_unit) (the reference's 10)."""

    weight_l1: float = 0.8
    weight_ssim: float = 0.2
    weight_depth: float = 0.1
    depth_unit: float = 10.0

    def validate(self) -> None:
        for name in ("weight_l1", "weight_ssim", "weight_depth"):
            require(getattr(self, name) >= 0, f"loss.{name}", ">= 0", getattr(self, name))
        require(self.depth_unit > 0, "loss.depth_unit", "> 0 metres", self.depth_unit)


class L1SSIMDepthLoss(MappingLoss):
    """See the module docstring."""

    def __init__(self, cfg: L1SSIMDepthConfig):
        self.cfg = cfg

    def __call__(self, render: RenderOutput, view: TrainingView) -> torch.Tensor:
        cfg = self.cfg
        mask = view.depth > 0
        has_depth = bool(mask.any())
        if not has_depth:
            mask = torch.ones_like(mask)
        m = mask.to(render.color.dtype)
        n = m.sum()
        loss = cfg.weight_l1 * (((render.color - view.image).abs() * m[..., None]).sum() / (3 * n))
        if cfg.weight_ssim:
            loss = loss + cfg.weight_ssim * (1 - image_metrics.ssim(render.color, view.image, mask, differentiable=True))
        if cfg.weight_depth and has_depth:
            loss = loss + cfg.weight_depth * (((render.depth - view.depth).abs() * m).sum() / n / cfg.depth_unit)
        return loss


@hookimpl
def slamkit_plugins():
    return [PluginSpec("l1_ssim_depth", L1SSIMDepthLoss, L1SSIMDepthConfig)]
