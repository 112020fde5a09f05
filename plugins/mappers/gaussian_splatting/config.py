"""The 3DGS mapper's own options (its parts have theirs: `rasterizer.*`, `sampler.*`,
`strategy.*`, `optimizer.*`, `loss.*`)."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.roles import PluginConfig, require
from slamkit_plugins.mappers.gaussian_splatting.keyframes import KeyframeStorage


@dataclass
class GaussianSplattingConfig(PluginConfig):
    """3DGS mapping options.

    resolution_scale: training images are the keyframes resized by this factor (area
      averaging; depth averaged over valid pixels). 0.5 by default (Replica's 1200x680 trains
      at 600x340, TUM's 640x480 at 320x240): a step costs about the number of (pixel,
      Gaussian) pairs, so 0.5 is 4x cheaper than full resolution, while 0.25 would cap the
      full-resolution PSNR near 30 dB on Replica (an ideal 0.25 image upsampled back scores
      30.2 dB on room0's frame 0; 0.5 scores 34.9 dB).
    coarse_steps: a keyframe's first training steps (this many) see it at half the training
      resolution: a step then costs about a quarter, spent while the keyframe's Gaussians are
      far from fitting it (coarse to fine; 0 = off, the paper's).
    keyframe_storage: memory | disk: where keyframe training images live (uint8 colour and
      uint16 millimetre depth at the training resolution either way; disk = .npy files read
      back when the keyframe is trained on, for long runs).
    keyframe_dir: folder for keyframe_storage=disk (null = a temporary folder, removed when the
      mapper is released; `mapper.keyframe_dir=${hydra:runtime.output_dir}/keyframes` keeps
      them in the run folder).
    eval_every: evaluate every n-th frame. eval_resolution_scale: resolution of evaluation
      renders (1 = the dataset's). save_images: number of render | ground-truth images written.
    seed: the training-view sampler's random generator.
    """

    resolution_scale: float = 0.5
    coarse_steps: int = 0
    keyframe_storage: KeyframeStorage = KeyframeStorage.memory
    keyframe_dir: str | None = None
    eval_every: int = 1
    eval_resolution_scale: float = 1.0
    save_images: int = 3
    seed: int = 0

    def validate(self) -> None:
        require(0 < self.resolution_scale <= 1, "mapper.resolution_scale", "in (0, 1]", self.resolution_scale)
        require(0 < self.eval_resolution_scale <= 1, "mapper.eval_resolution_scale", "in (0, 1]",
                self.eval_resolution_scale)
        require(self.coarse_steps >= 0, "mapper.coarse_steps", "an integer >= 0 (0 = off)", self.coarse_steps)
        require(self.eval_every >= 1, "mapper.eval_every", "an integer >= 1", self.eval_every)
        require(self.save_images >= 0, "mapper.save_images", "an integer >= 0", self.save_images)
        require(self.seed >= 0, "mapper.seed", "an integer >= 0 (numpy's generator seed)", self.seed)
