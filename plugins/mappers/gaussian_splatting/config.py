"""The 3DGS mapper's options: the trainer's (`.trainer.TrainerConfig`) and the
evaluation's. Its parts are groups nested under it: `mapper/rasterizer=cpu`,
`mapper.strategy.prune_every=400`."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.roles import require
from slamkit_plugins.mappers.gaussian_splatting.trainer import TrainerConfig


@dataclass
class GaussianSplattingConfig(TrainerConfig):
    """3DGS mapping of the shared map: training, then evaluation renders."""

    #: evaluate every n-th frame of the sequence
    eval_every: int = 1
    #: resolution of the evaluation renders relative to the dataset's
    eval_resolution_scale: float = 1.0
    #: render | ground-truth images written into the run folder
    save_images: int = 3

    def validate(self) -> None:
        super().validate()
        require(0 < self.eval_resolution_scale <= 1, "mapper.eval_resolution_scale", "in (0, 1]",
                self.eval_resolution_scale)
        require(self.eval_every >= 1, "mapper.eval_every", "an integer >= 1", self.eval_every)
        require(self.save_images >= 0, "mapper.save_images", "an integer >= 0", self.save_images)
