"""`slamkit mapper=gaussian_splatting` end to end on a tiny synthetic sequence: rendering
metrics, render images and the map. The mapper itself: tests/plugins/test_mapper.py."""

from __future__ import annotations

import json
import math

import pytest

from slamkit.formats.ply import load_ply

from support.commands import run_slamkit


@pytest.mark.slow
def test_cli_run_writes_rendering_metrics_images_and_map(tmp_path):
    """`mapper=gaussian_splatting` end to end on a tiny synthetic sequence."""
    out = tmp_path / "run"
    proc = run_slamkit(
        "dataset=synthetic", "dataset.num_frames=6", "dataset.width=64", "dataset.height=48",
        "tracker=gicp", "keyframe=every_n", "keyframe.tracking_every=3", "mapper=gaussian_splatting",
        "final_iterations=4", "mapper.save_images=2", "iterations_per_frame=2", "output.progress=false",
        f"hydra.run.dir={out}", cwd=tmp_path, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "psnr_train", "psnr_test", "depth_l1_cm"):
        assert math.isfinite(metrics[key]), key
    assert metrics["mapping_steps"] == 6 * 2 + 4 and metrics["eval_train_frames"] == 2
    assert len(load_ply(out / "map.ply")) == metrics["num_gaussians"] > 0
    assert len(list(out.glob("render_*.png"))) == 2
