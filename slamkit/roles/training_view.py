"""A keyframe as a training target (`TrainingView`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from slamkit.types import Camera


@dataclass
class TrainingView:
    """A keyframe as a training target, at the training resolution.

    keyframe_id, frame_index: which keyframe and input frame. pose: (4,4) float64
    camera-to-world. world_to_camera: (4,4) float32 tensor on the map's device (its inverse).
    camera: intrinsics in pixels at the training resolution. image: (H,W,3) float32 in [0, 1].
    depth: (H,W) float32 metres, 0 = invalid. Read-only: a trainer may hand the same view to
    several steps.
    """

    keyframe_id: int
    frame_index: int
    pose: np.ndarray
    world_to_camera: torch.Tensor
    camera: Camera
    image: torch.Tensor
    depth: torch.Tensor

    def window(self, x0: int, y0: int, width: int, height: int) -> TrainingView:
        """The view's pixels [x0, x0 + width) x [y0, y0 + height) as a view of its own: the same
        pose, the camera's principal point moved by (-x0, -y0) pixels."""
        if not (0 <= x0 and 0 <= y0 and 0 < width <= self.camera.width - x0 and 0 < height <= self.camera.height - y0):
            raise ValueError(f"window {width}x{height} at ({x0}, {y0}) is not inside the "
                             f"{self.camera.width}x{self.camera.height} view")
        camera = self.camera.cropped(x0, y0, width, height)
        rows, columns = slice(y0, y0 + height), slice(x0, x0 + width)
        return dataclasses.replace(self, camera=camera, image=self.image[rows, columns].contiguous(),
                                   depth=self.depth[rows, columns].contiguous())
