"""Rendering metrics of a trained map: every `every`-th frame rendered from its estimated pose.

PSNR / SSIM (and LPIPS, given its network) are masked by valid depth (`slamkit.metrics.images`,
`slamkit.metrics.lpips`; PSNR over the valid pixels or, `psnr_pixels="all"`, over every pixel
with the others zeroed, as the reference code) and reported for the keyframes (training views:
psnr_train, ssim_train, lpips_train), the other frames (held-out views: *_test) and all (psnr,
ssim, lpips; lpips null without the network); depth L1 in cm over valid pixels. A few render |
ground-truth images go into the run folder (written atomically).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from slamkit.map.gaussian_map import GaussianMap
from slamkit.metrics import images as image_metrics
from slamkit.metrics.lpips_network import LPIPS, min_image_side
from slamkit.progress import Progress
from slamkit.roles.rendering import RenderOutput
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.keyframes import resize_rgbd

log = logging.getLogger(__name__)


def evaluate_renders(render: Callable[[np.ndarray, Camera], RenderOutput], gaussian_map: GaussianMap, dataset,
                     poses: list[np.ndarray], train_frames: set[int], every: int = 1, scale: float = 1.0,
                     save_images: int = 0, out_dir: Path | None = None, lpips: LPIPS | None = None,
                     psnr_pixels: image_metrics.PsnrPixels | str = image_metrics.PsnrPixels.valid) -> dict[str, Any]:
    """Metrics of `render(pose, camera)` (no gradients) against every `every`-th frame of
    `dataset`, at `scale` of its resolution; `train_frames` are the keyframes' frame indices.
    LPIPS with `lpips` (None: recorded as null); PSNR over `psnr_pixels`. Writes `save_images`
    render | ground-truth images into `out_dir` (when given)."""
    n = min(len(dataset), len(poses))
    indices = list(range(0, n, every))
    camera = dataset[indices[0]].camera if lpips is not None and indices else None
    camera = camera.scaled(scale) if camera is not None and scale != 1.0 else camera
    if camera is not None and min(camera.width, camera.height) < min_image_side():
        log.warning("evaluation renders at %g of the frame size are below LPIPS's %d pixels a side: LPIPS is null",
                    scale, min_image_side())
        lpips = None
    n_img = min(save_images, len(indices))
    save_at = set(np.linspace(0, len(indices) - 1, n_img).round().astype(int).tolist()) if n_img else set()
    rows: dict[str, list[tuple[float, float, float]]] = {"all": [], "train": [], "test": []}
    depth_l1 = []
    start = time.perf_counter()
    bar = Progress("evaluation", len(indices), "view")
    for k, i in enumerate(indices):
        frame = dataset[i]
        image, depth, cam = resize_rgbd(frame.rgb, frame.depth, frame.camera, scale, gaussian_map.device)
        out = render(poses[i], cam)
        color = out.color.clamp(0, 1)
        mask = depth > 0
        scores = (image_metrics.psnr(color, image, mask, psnr_pixels), image_metrics.ssim(color, image, mask),
                  lpips(color, image, mask) if lpips is not None else math.nan)
        depth_l1.append(image_metrics.l1_depth(out.depth, depth, mask))
        rows["all"].append(scores)
        rows["train" if frame.index in train_frames else "test"].append(scores)
        if out_dir is not None and k in save_at:
            _save_side_by_side(Path(out_dir) / f"render_{i:04d}.png", color, image, out.depth, depth, frame.index,
                               scores[0])
        bar.update(1)
    bar.close()
    metrics: dict[str, Any] = {}
    for group, suffix in (("all", ""), ("train", "_train"), ("test", "_test")):
        metrics[f"psnr{suffix}"] = _finite_mean([p for p, _, _ in rows[group]])
        metrics[f"ssim{suffix}"] = _finite_mean([s for _, s, _ in rows[group]])
        metrics[f"lpips{suffix}"] = _finite_mean([d for _, _, d in rows[group]])
    l1 = _finite_mean(depth_l1)
    metrics.update(depth_l1_cm=None if l1 is None else 100.0 * l1, num_gaussians=len(gaussian_map),
                   eval_frames=len(indices), eval_train_frames=len(rows["train"]),
                   eval_time_s=time.perf_counter() - start)
    return metrics


def _finite_mean(values: list[float]) -> float | None:
    values = [v for v in values if math.isfinite(v)]
    return float(np.mean(values)) if values else None


#: The depth error that saturates the render images' error panel, metres.
DEPTH_ERROR_SCALE_M = 0.10


def _save_side_by_side(path: Path, render: torch.Tensor, truth: torch.Tensor, render_depth: torch.Tensor,
                       depth: torch.Tensor, frame: int, psnr: float) -> None:
    """render | input | depth error, each panel labelled above it (the render's PSNR; the
    frame; the error's scale: black 0, white DEPTH_ERROR_SCALE_M or more, blue no valid depth)."""
    from PIL import Image, ImageDraw

    from slamkit.formats.atomic import atomic_open

    valid = (depth > 0).unsqueeze(-1)
    error = ((render_depth - depth).abs() / DEPTH_ERROR_SCALE_M).clamp(0, 1).unsqueeze(-1).expand(*depth.shape, 3)
    no_depth = torch.tensor([0.1, 0.1, 0.4], device=error.device, dtype=error.dtype).expand_as(error)
    error = torch.where(valid, error, no_depth)
    panels = torch.cat([render.clamp(0, 1), truth.clamp(0, 1), error.to(render.dtype)], dim=1)
    pixels = (panels.cpu().numpy() * 255 + 0.5).astype(np.uint8)
    h, w = pixels.shape[0], pixels.shape[1] // 3
    strip = 14
    canvas = Image.new("RGB", (pixels.shape[1], h + strip), "black")
    canvas.paste(Image.fromarray(pixels), (0, strip))
    draw = ImageDraw.Draw(canvas)
    psnr_text = f"PSNR {psnr:.2f} dB" if math.isfinite(psnr) else "PSNR n/a"
    labels = (f"render, {psnr_text}", f"input, frame {frame}",
              f"depth error, 0-{100 * DEPTH_ERROR_SCALE_M:.0f} cm")
    for k, label in enumerate(labels):
        draw.text((k * w + 3, 1), label, fill="white")
    with atomic_open(path, "wb") as f:
        canvas.save(f, format="PNG")
