"""`mapper/loss=l1_ssim_depth`: GS-ICP SLAM's mapping loss (paper Eq. 9, as the reference code).

    loss = w_l1 L1(colour) + w_ssim (1 - SSIM(colour)) + w_depth L1(depth / 10 m)

over the pixels with valid observed depth (all pixels for the colour terms when none has
depth; no depth term then), or, with `pixels_without_depth=zero` as the reference code, over
every pixel with the observed colour and depth 0 where there is no depth (the torch backend).
L1 terms are means over those pixels (and the 3 channels); SSIM is pytorch-msssim's (window 11,
sigma 1.5) with the pixels outside the mask set to 0 in both images. The definition is
`torch_rgbd_loss` (`fused_rgbd_loss.py`); on CPU float32 images the compiled kernel computes the
same value and its gradients in one pass (`backend`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch

from slamkit.errors import ConfigError
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import (
    MappingLoss,
    PluginConfig,
    RenderOutput,
    RunContext,
    TrainingView,
    method_setting,
    require,
    thread_count,
)
from slamkit_plugins.mappers.gaussian_splatting.loss import fused_rgbd_loss as rgbd


class PixelsWithoutDepth(enum.Enum):
    """What the loss does at a pixel without observed depth. ignore: it is left out of every
    term. zero: it counts, its observed colour and depth taken as 0 (GS-ICP SLAM's reference
    code, which masks the ground-truth image only: the render is pulled towards black there)."""

    ignore = "ignore"
    zero = "zero"


class Backend(enum.Enum):
    """auto: the compiled kernel for CPU float32 images when it builds, else torch. compiled:
    the kernel or an error. torch: autograd through pytorch-msssim (the reference; GPU images)."""

    auto = "auto"
    compiled = "compiled"
    torch = "torch"


@dataclass
class L1SSIMDepthConfig(PluginConfig):
    """The paper's loss: L1 + SSIM on colour, L1 on depth."""

    #: weight of the colour L1 term (reference: 0.8)
    weight_l1: float = 0.8
    #: weight of the colour 1 - SSIM term (reference: 0.2)
    weight_ssim: float = 0.2
    #: weight of the depth L1 term (reference: 0.1)
    weight_depth: float = 0.1
    #: metres; the depth term is L1(depth / depth_unit) (the reference's 10)
    depth_unit: float = 10.0
    #: auto | compiled | torch: the same loss (see Backend)
    backend: Backend = Backend.auto
    #: the compiled kernel's threads (0: every CPU this process may use)
    num_threads: int = thread_count(0)
    #: pixels without depth: ignore (not counted) | zero (counted, depth 0; the reference code's, torch only)
    pixels_without_depth: PixelsWithoutDepth = method_setting(PixelsWithoutDepth.ignore)

    def validate(self) -> None:
        for name in ("weight_l1", "weight_ssim", "weight_depth"):
            require(getattr(self, name) >= 0, f"mapper.loss.{name}", ">= 0", getattr(self, name))
        require(self.depth_unit > 0, "mapper.loss.depth_unit", "> 0 metres", self.depth_unit)
        require(self.num_threads >= 0, "mapper.loss.num_threads", "an integer >= 0 (0: every CPU)",
                self.num_threads)


class L1SSIMDepthLoss(MappingLoss):
    """See the module docstring."""

    def __init__(self, cfg: L1SSIMDepthConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        backend = Backend(cfg.backend)
        self.all_pixels = PixelsWithoutDepth(cfg.pixels_without_depth) is PixelsWithoutDepth.zero
        if backend is Backend.compiled and self.all_pixels:
            raise ConfigError("mapper.loss.backend=compiled: the kernel computes pixels_without_depth=ignore only "
                              "(use backend=auto or torch with pixels_without_depth=zero)")
        if backend is Backend.compiled and not rgbd.available():
            raise ConfigError(f"mapper.loss.backend=compiled: the kernel is not available ({rgbd.LIBRARY.error})")
        self.compiled = backend is not Backend.torch and not self.all_pixels and rgbd.available()

    def __call__(self, render: RenderOutput, view: TrainingView) -> torch.Tensor:
        c = self.cfg
        args = (render.color, render.depth, view.image, view.depth, c.weight_l1, c.weight_ssim, c.weight_depth,
                c.depth_unit)
        on_cpu = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in args[:4])
        if self.compiled and on_cpu:
            return rgbd.fused_rgbd_loss(*args, num_threads=c.num_threads)
        return rgbd.torch_rgbd_loss(*args, all_pixels=self.all_pixels)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("l1_ssim_depth", L1SSIMDepthLoss, L1SSIMDepthConfig)]
