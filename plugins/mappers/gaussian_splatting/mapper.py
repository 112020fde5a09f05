"""`mapper=gaussian_splatting`: GS-ICP SLAM's 3DGS mapper (paper Sec. 3.2): a
`slamkit.splatting.Trainer` composed of the parts chosen on the command line
(`mapper/rasterizer=`, `mapper/sampler=`, `mapper/strategy=`, `mapper/optimizer=`,
`mapper/loss=`), the map written as a 3DGS PLY, and the map's renders evaluated against the
sequence, scored as the run says (`RunContext.scoring`: the run's eval.lpips, eval.lpips_backbone,
eval.psnr_pixels; the LPIPS network is loaded when the mapper is built, so eval.lpips=on without
its weights stops the run before any work)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slamkit.config import RunContext
from slamkit.formats.ply import save_ply
from slamkit.metrics.images import PsnrPixels
from slamkit.metrics.lpips import lpips_for_evaluation
from slamkit.roles import KeyframeSampler, MapOptimizer, Mapper, MappingLoss, Rasterizer, RenderOutput, Strategy
from slamkit.splatting import Trainer
from slamkit.splatting.evaluation import evaluate_renders
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.config import GaussianSplattingConfig


class GaussianSplattingMapper(Mapper):
    """3DGS mapping of the shared GaussianMap from keyframe images; `trainer` trains it."""

    parts = ("rasterizer", "sampler", "strategy", "optimizer", "loss")

    def __init__(self, cfg: GaussianSplattingConfig, context: RunContext = RunContext(), *, rasterizer: Rasterizer,
                 sampler: KeyframeSampler, strategy: Strategy, optimizer: MapOptimizer, loss: MappingLoss):
        super().__init__(cfg, context)
        self.trainer = Trainer(cfg, self.gaussian_map, rasterizer, sampler, strategy, optimizer, loss)
        scoring = context.scoring
        self.psnr_pixels = PsnrPixels(scoring.psnr_pixels)
        self.lpips = lpips_for_evaluation(scoring.lpips, scoring.lpips_backbone, self.gaussian_map.device)

    def admit(self, frame, pose, new):
        return self.trainer.admit(frame, pose, new)

    def add_keyframe(self, frame, pose, kind, new_rows) -> None:
        self.trainer.add_keyframe(frame, pose, kind, new_rows)

    def move_keyframes(self, updates) -> None:
        self.trainer.move_keyframes(updates)

    def optimize(self, iterations: int) -> int:
        return self.trainer.train(iterations)

    def finish(self) -> None:
        self.trainer.finish()

    def state_dict(self) -> dict[str, Any]:
        return self.trainer.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.trainer.load_state_dict(state)

    def render_view(self, pose: np.ndarray, camera: Camera) -> RenderOutput:
        return self.trainer.render_view(pose, camera)

    def save_map(self, out_dir) -> list[Path]:
        """map.ply (the 3DGS PLY layout) of the map as it stands, taken under the map's lock."""
        path = Path(out_dir) / "map.ply"
        with self.gaussian_map.lock:
            save_ply(path, self.gaussian_map)
        return [path]

    def evaluate(self, dataset, poses: list[np.ndarray], out_dir) -> dict[str, Any]:
        cfg, keyframes = self.cfg, self.trainer.keyframes
        train_frames = {kf.frame_index for kf in keyframes.values()}
        metrics = evaluate_renders(self.render_view, self.gaussian_map, dataset, poses, train_frames,
                                   cfg.eval_every, cfg.eval_resolution_scale, cfg.save_images, out_dir,
                                   self.lpips, self.psnr_pixels)
        return {**metrics, **self.trainer.metrics()}
