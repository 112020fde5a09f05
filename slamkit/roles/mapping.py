"""The mapping roles: the mapper, and the parts a mapper may be composed of (training-view
sampler, loss, optimiser; the rasteriser is `slamkit.map.rendering.Rasterizer`, the densification
strategy `slamkit.roles.strategy.DensifyStrategy`)."""

from __future__ import annotations

from abc import ABC, abstractmethod
import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import numpy as np
import torch

from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.map.rendering import RenderOutput
from slamkit.types import Camera, Frame, KeyframeKind, TrackingResult


class Mapper(ABC):
    """Optimises the shared Gaussian map from keyframe images.

    `parts` names the mapper parts (role keys of `slamkit.roles.ROLES`, e.g. "rasterizer")
    that its constructor takes as keyword arguments after its config; the pipeline builds each
    from the run's config (`rasterizer=cpu rasterizer.num_threads=2`)."""

    parts: ClassVar[tuple[str, ...]] = ()

    def bind(self, gaussian_map: GaussianMap) -> None:
        """Called once with the shared map before the first frame."""
        self.gaussian_map = gaussian_map

    def use_mode(self, realtime: bool) -> None:
        """Whether the run is in real-time mode (mapping beside tracking while the input
        streams), given before the first frame: a mapper may choose the defaults of its null
        options by it. The default ignores it."""

    def admit(self, frame: Frame, pose: np.ndarray, new: GaussianRows) -> torch.Tensor | np.ndarray | None:
        """Which of a keyframe's new Gaussians (scale-aligned, not yet in the map) enter it: a
        bool mask over `new`, or None for all (the default). `pose` is the keyframe's
        camera-to-world pose. Called under the map's lock; the rows it admits are appended next
        (their shapes, which `new` computes when first read, computed in between, outside the
        lock)."""
        return None

    @abstractmethod
    def add_keyframe(self, frame: Frame, result: TrackingResult, kind: KeyframeKind, new_rows: slice) -> None:
        """Register a keyframe; `new_rows` are the map rows its Gaussians were added at."""

    @abstractmethod
    def optimize(self, iterations: int) -> int:
        """Run up to `iterations` optimisation steps; return how many were done."""

    def finish(self) -> None:
        """Called once after the last frame and any refinement steps (`optimize` calls), to
        wrap up (e.g. a last pruning)."""

    def save_map(self, out_dir) -> list:
        """Write the map as trained so far into the folder `out_dir` (e.g. map.ply) and return
        the paths written; [] (the default) for a mapper that keeps no map. Called after the
        refinement, and when the run stops early, with no mapping step running."""
        return []

    def evaluate(self, frames, poses: list[np.ndarray], out_dir) -> dict[str, Any]:
        """Rendering metrics (psnr, ssim, ...) for the run's metrics.json; {} if none. Called
        after `save_map`; may write images into `out_dir` (None: write nothing)."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        """What the mapper needs to go on training where a run stopped (saved in the map
        checkpoint beside the map's rows, `slamkit.run.checkpoint`): its keyframes, optimiser
        and strategy state, counters; JSON values and arrays (numpy or torch). {} by default."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()` (arrays as numpy arrays or CPU tensors), after `bind` and
        after the map's rows are restored. Nothing by default."""

    def render_view(self, pose: np.ndarray, camera: Camera) -> RenderOutput | None:
        """The map as this mapper renders it from `pose` (4x4 camera-to-world, metres) for
        `camera`, without gradients (for viewers); None when the mapper cannot render (the
        default). Must be safe to call beside a mapping thread."""
        return None


@dataclass
class TrainingView:
    """A keyframe as a training target, at the training resolution.

    keyframe_id, frame_index: which keyframe and input frame. pose: (4,4) float64
    camera-to-world. world_to_camera: (4,4) float32 tensor on the map's device (its inverse).
    camera: intrinsics in pixels at the training resolution. image: (H,W,3) float32 in [0, 1].
    depth: (H,W) float32 metres, 0 = invalid. Read-only: a mapper may hand the same view to
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


class KeyframeSampler(ABC):
    """Chooses which keyframe the mapper trains on next."""

    @abstractmethod
    def sample(self, keyframe_ids: list[int], current_pose: np.ndarray, rng: np.random.Generator,
               keyframe_poses: dict[int, np.ndarray]) -> int:
        """One of `keyframe_ids` (non-empty, in arrival order). current_pose (the newest
        keyframe's) and keyframe_poses (id -> pose) are camera-to-world 4x4; a sampler that needs
        no geometry ignores them."""


class MappingLoss(ABC):
    """What a training step minimises: a render compared with its keyframe."""

    @abstractmethod
    def __call__(self, render: RenderOutput, view: TrainingView) -> torch.Tensor:
        """A 0-d tensor, differentiable with respect to the render's colour and depth."""


class MapOptimizer(ABC):
    """Updates the map's parameters from one training step's gradients.

    Its state is per map row (e.g. Adam's moments), so it must follow the rows as the map grows
    and shrinks: the shared row operations (`slamkit.map.editing.MapEdit`) call `edit_rows` and
    `reset`, never a strategy directly."""

    @abstractmethod
    def step(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> None:
        """Update `params` (the map's leaf tensors by name, `slamkit.map.gaussian_map.PARAMETERS`)
        in place from `grads` (same names and shapes; a missing name had no gradient)."""

    @abstractmethod
    def num_rows(self) -> int:
        """The map rows its state covers."""

    @abstractmethod
    def edit_rows(self, edit: Callable[[str, torch.Tensor], torch.Tensor]) -> None:
        """Replace each per-row state tensor `v` of parameter `name` by `edit(name, v)` (first
        dimension = rows; the result may have a different number of rows)."""

    @abstractmethod
    def reset(self) -> None:
        """Forget all state (zero rows)."""

    def state_dict(self) -> dict[str, Any]:
        """The optimiser's state (per-row moments, step counts) for a map checkpoint: JSON values
        and tensors."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()` (CPU tensors; `edit_rows` moves them to the map's device)."""

    def row_state(self) -> dict[str, list[torch.Tensor]]:
        """Copies of the per-row state tensors, by parameter name (for inspection and tests)."""
        found: dict[str, list[torch.Tensor]] = {}

        def copy(name: str, v: torch.Tensor) -> torch.Tensor:
            found.setdefault(name, []).append(v.clone())
            return v

        self.edit_rows(copy)
        return found
