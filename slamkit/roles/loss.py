"""The loss part: what a training step minimises."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch

from slamkit.roles.rendering import RenderOutput
from slamkit.roles.training_view import TrainingView


class MappingLoss(ABC):
    """A render compared with its keyframe."""

    @abstractmethod
    def __call__(self, render: RenderOutput, view: TrainingView) -> torch.Tensor:
        """A 0-d tensor, differentiable with respect to the render's colour and depth."""
