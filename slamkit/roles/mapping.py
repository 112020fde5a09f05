"""The mapper role: optimises the shared Gaussian map from keyframe images. A mapper may be
composed of parts (`Mapper.parts`: the 3DGS mapper's rasteriser, sampler, strategy, optimiser,
loss), each a plugin kind of its own whose config group is nested under the mapper's
(`mapper/rasterizer=cpu`)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np
import torch

from slamkit.config import PluginConfig, RunContext
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.roles.rendering import RenderOutput
from slamkit.types import Camera, Frame, KeyframeKind


class Mapper(ABC):
    """Optimises the shared Gaussian map (`context.gaussian_map`) from keyframe images.

    Built as `cls(config, context, **parts)`: `parts` names the mapper's parts (part keys of
    `slamkit.roles.ROLES`, e.g. "rasterizer"); the registry builds each from the mapper's nested
    config (`mapper.rasterizer`, chosen with `mapper/rasterizer=NAME`) and passes it by name."""

    parts: ClassVar[tuple[str, ...]] = ()
    #: whether the map grows with a keyframe's every Gaussian made from its pixels when the tracker
    #: hands none over (`slamkit.map.growth.frame_gaussians`); false for a mapper that renders
    #: nothing and keeps only what a Gaussian-map tracker hands over
    grows_from_frames: ClassVar[bool] = True

    def __init__(self, cfg: PluginConfig | None = None, context: RunContext = RunContext(), **parts: Any):
        self.cfg = cfg
        self.gaussian_map: GaussianMap = context.gaussian_map if context.gaussian_map is not None else GaussianMap()

    def admit(self, frame: Frame, pose: np.ndarray, new: GaussianRows) -> torch.Tensor | np.ndarray | None:
        """Which of a keyframe's new Gaussians (scale-aligned, not yet in the map) enter it: a
        bool mask over `new`, or None for all (the default). `pose` is the keyframe's
        camera-to-world pose. The trackable ones enter whatever it answers (they are the
        tracker's target); in real time they have entered already (rows of `new.keyframe_id` in
        the map) and `new` holds the others only. Called under the map's lock; the rows it admits
        are appended next."""
        return None

    @abstractmethod
    def add_keyframe(self, frame: Frame, pose: np.ndarray, kind: KeyframeKind, new_rows: slice) -> None:
        """Register a keyframe seen from `pose` (camera-to-world); `new_rows` are the map rows
        its Gaussians were added at. In real time it runs in a thread of its own beside tracking
        and training (`admit` of the next keyframe waits for it)."""

    @abstractmethod
    def optimize(self, iterations: int) -> int:
        """Run up to `iterations` optimisation steps; return how many were done."""

    def move_keyframes(self, updates: np.ndarray) -> None:
        """A loop closure corrected the keyframes: keyframe k (the k-th `add_keyframe`, the id
        its Gaussians carry in `GaussianMap.keyframe_id`) moved by the world-frame rigid motion
        `updates[k]` ((K,4,4), corrected pose = updates[k] @ pose). Move its Gaussians with it
        and whatever the mapper keeps of it (training views' poses, per-row optimiser state).
        The default moves the map's rows alone (`GaussianMap.move_rows`); an override must move
        them too. Called from the tracking thread, between two frames."""
        self.gaussian_map.move_rows(self.gaussian_map.keyframe_motion(updates))

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
        checkpoint beside the map's rows, `slamkit.run.checkpoint`): JSON values and arrays
        (numpy or torch). {} by default."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()` (arrays as numpy arrays or CPU tensors), after the map's
        rows are restored. Nothing by default."""

    def render_view(self, pose: np.ndarray, camera: Camera) -> RenderOutput | None:
        """The map as this mapper renders it from `pose` (4x4 camera-to-world, metres) for
        `camera`, without gradients (for viewers); None when the mapper cannot render (the
        default). Must be safe to call beside a mapping thread."""
        return None
