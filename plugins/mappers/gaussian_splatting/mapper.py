"""`mapper=gaussian_splatting`: GS-ICP SLAM's 3DGS mapper (paper Sec. 3.2): the trainer
(`.trainer.Trainer`, itself a `Mapper`) composed of the parts chosen on the command line
(`mapper/rasterizer=`, `mapper/sampler=`, `mapper/strategy=`, `mapper/optimizer=`,
`mapper/loss=`), with the map written as a 3DGS PLY and the map's renders evaluated against the
sequence, scored as the run says (`RunContext.scoring`: the run's eval.lpips, eval.lpips_backbone,
eval.psnr_pixels; the LPIPS network is loaded when the mapper is built, so eval.lpips=on without
its weights stops the run before any work)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slamkit.config import RunContext
from slamkit.formats.ply import save_ply
from slamkit.metrics.lpips import lpips_for_evaluation
from slamkit_plugins.mappers.gaussian_splatting.config import GaussianSplattingConfig
from slamkit_plugins.mappers.gaussian_splatting.evaluation import evaluate_renders
from slamkit_plugins.mappers.gaussian_splatting.trainer import Trainer


class GaussianSplattingMapper(Trainer):
    """3DGS mapping of the shared GaussianMap from keyframe images: the trainer, its map's file
    and evaluation."""

    parts = ("rasterizer", "sampler", "strategy", "optimizer", "loss")

    def __init__(self, cfg: GaussianSplattingConfig, context: RunContext = RunContext(), **parts: Any):
        super().__init__(cfg, context, **parts)
        scoring = context.scoring
        self.psnr_pixels = scoring.psnr_pixels
        self.lpips = lpips_for_evaluation(scoring.lpips, scoring.lpips_backbone, self.gaussian_map.device)

    def save_map(self, out_dir) -> list[Path]:
        """map.ply (the 3DGS PLY layout) of the map as it stands, taken under the map's lock."""
        path = Path(out_dir) / "map.ply"
        with self.gaussian_map.lock:
            save_ply(path, self.gaussian_map)
        return [path]

    def evaluate(self, dataset, poses: list[np.ndarray], out_dir) -> dict[str, Any]:
        cfg = self.cfg
        train_frames = {kf.frame_index for kf in self.keyframes.values()}
        metrics = evaluate_renders(self.render_view, self.gaussian_map, dataset, poses, train_frames,
                                   cfg.eval_every, cfg.eval_resolution_scale, cfg.save_images, out_dir,
                                   self.lpips, self.psnr_pixels)
        return {**metrics, **self.metrics()}
