"""The 3DGS mapper's own options (its parts have theirs: `rasterizer.*`, `sampler.*`,
`strategy.*`, `optimizer.*`, `loss.*`)."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.roles import PluginConfig, require
from slamkit_plugins.mappers.gaussian_splatting.keyframes import KeyframeStorage


#: `resolution_scale` when null, by mode (see GaussianSplattingConfig).
SEQUENTIAL_RESOLUTION_SCALE = 0.5
REALTIME_RESOLUTION_SCALE = 0.25


@dataclass
class GaussianSplattingConfig(PluginConfig):
    """3DGS mapping options.

    resolution_scale: training images are the keyframes resized by this factor (area
      averaging; depth averaged over valid pixels). When null, 0.5 (Replica's 1200x680 trains
      at 600x340, TUM's 640x480 at 320x240), and 0.25 in real-time mode. A step costs about the
      number of (pixel, Gaussian) pairs, so 0.5 is 4x cheaper than full resolution, while 0.25
      caps the full-resolution PSNR near 30 dB on Replica (an ideal 0.25 image upsampled back
      scores 30.2 dB on room0's frame 0; 0.5 scores 34.9 dB): a sequential run, which trains
      long, keeps 0.5; a real-time run, whose map gets a few steps a keyframe, is better off with
      twice the steps at 0.25 (docs/results.md, "Real time on an AVX2 CPU").
    coarse_steps: a keyframe's first training steps (this many) see it at half the training
      resolution: a step then costs about a quarter, spent while the keyframe's Gaussians are
      far from fitting it (coarse to fine; 0 = off, the paper's).
    window: a step trains on a random window of its view, this fraction of its width and of its
      height (at least 16 pixels a side; render, loss and gradients only there: a step costs
      about the window's area; 1 = the whole view, 3DGS's step). The loss is a mean over the
      window's pixels, so `strategy=3dgs`'s gradient statistic grows by about 1 / window (its
      grad_threshold is per window).
    keyframe_storage: memory | disk: where keyframe training images live (uint8 colour and
      uint16 millimetre depth at the training resolution either way; disk = .npy files read
      back when the keyframe is trained on, for long runs).
    keyframe_dir: folder for keyframe_storage=disk (null = a temporary folder, removed when the
      mapper is released; `mapper.keyframe_dir=${hydra:runtime.output_dir}/keyframes` keeps
      them in the run folder).
    view_cache_mb: training views (the keyframes' images as float tensors on the map's device)
      kept between steps, at most this many MiB, least recently used dropped first: a step on a
      kept view skips converting its keyframe's images (~1 ms of a 27 ms step at 320x240). 64
      MiB holds ~50 views at 320x240, ~20 at 600x340 (0 = off). Not counted in the metrics'
      keyframe_memory_mb.
    eval_every: evaluate every n-th frame. eval_resolution_scale: resolution of evaluation
      renders (1 = the dataset's). save_images: number of render | ground-truth images written.
    seed: the training-view sampler's random generator.
    """

    resolution_scale: float | None = None
    coarse_steps: int = 0
    window: float = 1.0
    keyframe_storage: KeyframeStorage = KeyframeStorage.memory
    keyframe_dir: str | None = None
    view_cache_mb: float = 64.0
    eval_every: int = 1
    eval_resolution_scale: float = 1.0
    save_images: int = 3
    seed: int = 0

    def validate(self) -> None:
        require(self.resolution_scale is None or 0 < self.resolution_scale <= 1, "mapper.resolution_scale",
                "null or in (0, 1]", self.resolution_scale)
        require(0 < self.eval_resolution_scale <= 1, "mapper.eval_resolution_scale", "in (0, 1]",
                self.eval_resolution_scale)
        require(0 < self.window <= 1, "mapper.window", "in (0, 1]", self.window)
        require(self.coarse_steps >= 0, "mapper.coarse_steps", "an integer >= 0 (0 = off)", self.coarse_steps)
        require(self.view_cache_mb >= 0, "mapper.view_cache_mb", "a size in MiB >= 0 (0 = off)", self.view_cache_mb)
        require(self.eval_every >= 1, "mapper.eval_every", "an integer >= 1", self.eval_every)
        require(self.save_images >= 0, "mapper.save_images", "an integer >= 0", self.save_images)
        require(self.seed >= 0, "mapper.seed", "an integer >= 0 (numpy's generator seed)", self.seed)

    def training_scale(self, realtime: bool) -> float:
        """`resolution_scale`, or its default for the run's mode when null."""
        if self.resolution_scale is not None:
            return self.resolution_scale
        return REALTIME_RESOLUTION_SCALE if realtime else SEQUENTIAL_RESOLUTION_SCALE
