"""`mapper=gaussian_splatting`: 3D Gaussian Splatting mapping on the shared map (paper Sec. 3.2).

The mapper optimises the GaussianMap the tracker aligns to. Keyframe Gaussians enter the map
through the core (`slamkit.map_growth`: opacity 0.1, the G-ICP covariance scale-aligned by depth);
this mapper keeps each keyframe's image and depth (downscaled to the training resolution) and
its estimated pose (camera-to-world, not refined), and trains:

- each new keyframe once on arrival, then keyframes drawn by a KeyframeSampler (`sampler`,
  `random` by default, as the paper: Table 8a);
- loss 0.8 L1(rgb) + 0.2 (1 - SSIM) + 0.1 L1(depth / 10), over the pixels with valid depth
  (SSIM window 11, sigma 1.5, the invalid pixels set to 0 in both images);
- Adam (eps 1e-15) with the reference code's learning rates: means 4e-6 (constant), colour
  0.0025, opacity 0.05, scale 0.005, rotation 0.001 (the parameters are the map's raw 3DGS
  tensors: means, quats (w,x,y,z), log_scales, opacity_logits, colors);
- pruning every `prune_every` steps: opacity < `prune_min_opacity` or largest scale >
  `max_scale` metres (the dataset's hint: 0.25 Replica, 1.0 TUM). No densification and no
  opacity reset unless asked (`densify`, `opacity_reset`, for the paper's Table 8b ablation);
- a memory guard (`max_gaussians`, off by default): when keyframes (or densification) take the
  map above the cap, the least opaque Gaussians are pruned, through the same path as pruning.

Keyframe images are kept at the training resolution as uint8 colour and uint16 depth (1 mm
steps), in memory or, with `keyframe_storage=disk`, as .npy files read back when sampled: a
long run holds hundreds of keyframes.

Shared state. The optimised parameters ARE the GaussianMap's tensors (leaf tensors with
requires_grad, updated in place), so the tracker's `tracking_target()` at the next tracking
keyframe copies the optimised means and covariances: that exchange is the point of the method.
Every step runs under `gaussian_map.lock` and bumps `gaussian_map.version`. The Adam moments
are kept per map row and follow the map: rows the core appends (new keyframe Gaussians) get
fresh moments, rows this mapper removes (pruning) lose theirs; each row has its own step count,
so a new Gaussian's first update is bias-corrected like any first Adam step. A step whose loss
or gradient is not finite is skipped (parameters and moments unchanged).

Evaluation (`evaluate`, after the run): every `eval_every`-th frame rendered from its estimated
pose at `eval_resolution_scale`; PSNR / SSIM masked by valid depth (`slamkit.image_metrics`),
reported for keyframes (training views: psnr_train, ssim_train), the other frames (held-out
views: psnr_test, ssim_test) and all (psnr, ssim); depth L1 in cm over valid pixels; a few
render | ground-truth images and `map.ply` in the run folder.
"""

from __future__ import annotations

import enum
import inspect
import logging
import math
import shutil
import tempfile
import time
import weakref
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from slamkit import image_metrics
from slamkit.gaussian_map import GaussianMap
from slamkit.geometry import invert_pose, quat_to_rotmat
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.rendering import Rasterizer, RenderOutput, render_map
from slamkit.roles import Mapper, PluginConfig, require
from slamkit.types import Camera, Frame, KeyframeKind, TrackingResult

log = logging.getLogger(__name__)

#: Parameter name in GaussianMap -> learning-rate field of the config.
_LR_FIELDS = {
    "means": "lr_means",
    "quats": "lr_quats",
    "log_scales": "lr_scales",
    "opacity_logits": "lr_opacity",
    "colors": "lr_colors",
}
#: Used when `max_scale` is null and the dataset gives no hint (metres).
FALLBACK_MAX_SCALE = 1.0
#: The depth term is L1(depth / DEPTH_UNIT) (metres / 10, as the reference code).
DEPTH_UNIT = 10.0
#: Keyframe depth is stored as uint16 in steps of this many metres (1 mm: at most 0.5 mm of
#: rounding, up to 65.5 m; deeper pixels are stored as invalid).
KEYFRAME_DEPTH_STEP = 1e-3


class KeyframeStorage(enum.Enum):
    """Where keyframe training images live: memory, or disk (.npy files)."""

    memory = "memory"
    disk = "disk"


@dataclass
class GaussianSplattingConfig(PluginConfig):
    """3DGS mapping options.

    rasterizer: auto | torch | cpu | gsplat (auto = gsplat on CUDA, else cpu, else torch).
    sampler: keyframe sampler for the training schedule: random | covisible | recent.
    lr_means, lr_colors, lr_opacity, lr_scales, lr_quats: Adam learning rates (reference code:
      4e-6, 0.0025, 0.05, 0.005, 0.001; scales and opacity in log / logit space).
    adam_eps: Adam epsilon (1e-15 as 3DGS).
    weight_l1, weight_ssim, weight_depth: loss = w_l1 L1(rgb) + w_ssim (1 - SSIM) +
      w_depth L1(depth / 10 m), over pixels with valid depth.
    resolution_scale: training images are the keyframes resized by this factor (area
      averaging; depth averaged over valid pixels). 0.5 by default (Replica's 1200x680 trains
      at 600x340, TUM's 640x480 at 320x240): a step costs about the number of (pixel,
      Gaussian) pairs, so 0.5 is 4x cheaper than full resolution, while 0.25 would cap the
      full-resolution PSNR near 30 dB on Replica (an ideal 0.25 image upsampled back scores
      30.2 dB on room0's frame 0; 0.5 scores 34.9 dB).
    final_iterations: sampled training steps after the last frame (in `finish`). 400 by
      default, so that a short sequence (20 Replica frames at 10 steps a frame) is trained
      for ~600 steps in all: the training views' PSNR is still rising at 350 steps.
    prune_every: steps between prunings (0 = never). prune_min_opacity: prune below this.
    max_scale: metres; prune Gaussians whose largest scale exceeds it (null = the dataset's
      hint, else 1.0).
    densify: 3DGS clone / split densification (ablation; off in GS-ICP SLAM), every
      `densify_every` steps, for Gaussians whose average view-space positional gradient
      (approximated from the 3D gradient, in 3DGS's NDC units) reaches `densify_grad_threshold`:
      cloned when their largest scale is <= `densify_scale_threshold` metres, else split in two
      (scales / 1.6). No densification beyond `densify_max_gaussians` Gaussians.
    opacity_reset: every `opacity_reset_every` steps, opacities above 0.01 are set to 0.01
      (3DGS; ablation).
    skip_covered: do not grow the map where it already covers a keyframe pixel: a new
      Gaussian is dropped when the map rendered at the keyframe's pose (training resolution)
      has alpha > `covered_alpha` at its pixel and an expected depth (depth / alpha) within
      `covered_depth_tolerance` metres of its own.
    max_gaussians: memory guard, null = unlimited (the paper's behaviour). When a keyframe's
      Gaussians (or densification) take the map above this many, the least opaque Gaussians
      (lowest opacity; the keyframe's own new Gaussians, whose opacity is still the initial
      value and says nothing yet, go last) are pruned until (1 - memory_guard_margin) x
      max_gaussians remain, so a guarded run does not prune at every keyframe. Off by default:
      the cap changes the map (and so the results) and the right size depends on the machine:
      a Gaussian costs up to ~1 kB of resident memory while mapping (parameters, Adam moments,
      the rasteriser's per-step buffers; 0.7-0.9 kB measured, docs/results.md), so 1,000,000
      is about 1 GB.
    memory_guard_margin: fraction of max_gaussians freed below the cap when the guard prunes.
    keyframe_storage: memory | disk: where keyframe training images live (uint8 colour and
      uint16 millimetre depth at the training resolution either way; disk = .npy files read
      back when the keyframe is trained on, for long runs).
    keyframe_dir: folder for keyframe_storage=disk (null = a temporary folder, removed when the
      mapper is released; `mapper.keyframe_dir=${hydra:runtime.output_dir}/keyframes` keeps
      them in the run folder).
    eval_every: evaluate every n-th frame. eval_resolution_scale: resolution of evaluation
      renders (1 = the dataset's). save_images: number of render | ground-truth images written.
    seed: the sampler's random generator.
    """

    rasterizer: str = "auto"
    sampler: str = "random"
    lr_means: float = 4e-6
    lr_colors: float = 0.0025
    lr_opacity: float = 0.05
    lr_scales: float = 0.005
    lr_quats: float = 0.001
    adam_eps: float = 1e-15
    weight_l1: float = 0.8
    weight_ssim: float = 0.2
    weight_depth: float = 0.1
    resolution_scale: float = 0.5
    final_iterations: int = 400
    prune_every: int = 200
    prune_min_opacity: float = 0.005
    max_scale: float | None = None
    densify: bool = False
    densify_every: int = 100
    densify_grad_threshold: float = 0.0002
    densify_scale_threshold: float = 0.05
    densify_max_gaussians: int = 2_000_000
    opacity_reset: bool = False
    opacity_reset_every: int = 3000
    skip_covered: bool = False
    covered_alpha: float = 0.9
    covered_depth_tolerance: float = 0.05
    max_gaussians: int | None = None
    memory_guard_margin: float = 0.1
    keyframe_storage: KeyframeStorage = KeyframeStorage.memory
    keyframe_dir: str | None = None
    eval_every: int = 1
    eval_resolution_scale: float = 1.0
    save_images: int = 3
    seed: int = 0

    def validate(self) -> None:
        for name in _LR_FIELDS.values():
            v = getattr(self, name)
            require(v >= 0 and math.isfinite(v), f"mapper.{name}", "a learning rate >= 0", v)
        require(self.adam_eps > 0, "mapper.adam_eps", "> 0", self.adam_eps)
        for name in ("weight_l1", "weight_ssim", "weight_depth"):
            require(getattr(self, name) >= 0, f"mapper.{name}", ">= 0", getattr(self, name))
        require(0 < self.resolution_scale <= 1, "mapper.resolution_scale", "in (0, 1]", self.resolution_scale)
        require(0 < self.eval_resolution_scale <= 1, "mapper.eval_resolution_scale", "in (0, 1]",
                self.eval_resolution_scale)
        require(self.final_iterations >= 0, "mapper.final_iterations", "an integer >= 0", self.final_iterations)
        require(self.prune_every >= 0, "mapper.prune_every", "an integer >= 0 (0 = never)", self.prune_every)
        require(0 <= self.prune_min_opacity < 1, "mapper.prune_min_opacity", "in [0, 1)", self.prune_min_opacity)
        require(self.max_scale is None or self.max_scale > 0, "mapper.max_scale", "null or > 0 metres", self.max_scale)
        require(self.densify_every >= 1, "mapper.densify_every", "an integer >= 1", self.densify_every)
        require(self.densify_grad_threshold > 0, "mapper.densify_grad_threshold", "> 0", self.densify_grad_threshold)
        require(self.densify_scale_threshold > 0, "mapper.densify_scale_threshold", "> 0 metres",
                self.densify_scale_threshold)
        require(self.densify_max_gaussians >= 0, "mapper.densify_max_gaussians", ">= 0", self.densify_max_gaussians)
        require(self.opacity_reset_every >= 1, "mapper.opacity_reset_every", "an integer >= 1",
                self.opacity_reset_every)
        require(0 < self.covered_alpha < 1, "mapper.covered_alpha", "in (0, 1)", self.covered_alpha)
        require(self.covered_depth_tolerance > 0, "mapper.covered_depth_tolerance", "> 0 metres",
                self.covered_depth_tolerance)
        require(self.max_gaussians is None or self.max_gaussians > 0, "mapper.max_gaussians",
                "null (unlimited) or an integer > 0", self.max_gaussians)
        require(0 <= self.memory_guard_margin < 1, "mapper.memory_guard_margin", "in [0, 1)",
                self.memory_guard_margin)
        require(self.eval_every >= 1, "mapper.eval_every", "an integer >= 1", self.eval_every)
        require(self.save_images >= 0, "mapper.save_images", "an integer >= 0", self.save_images)


@dataclass
class Keyframe:
    """A training view at the training resolution: its camera, pose (camera-to-world, float64)
    and inverse (float32 tensor), and its image (h,w,3) uint8 and depth (h,w) uint16 in
    KEYFRAME_DEPTH_STEP metres (0 = invalid), held in `rgbd` or, when `path` is set, in
    `path`_rgb.npy / `path`_depth.npy (read on each use)."""

    id: int
    frame_index: int
    kind: KeyframeKind
    pose: np.ndarray
    world_to_camera: torch.Tensor
    camera: Camera
    rgbd: tuple[np.ndarray, np.ndarray] | None = None
    path: Path | None = None

    @classmethod
    def store(cls, image: torch.Tensor, depth: torch.Tensor, path: Path | None = None, **fields) -> Keyframe:
        """Quantise `image` (h,w,3) float in [0,1] and `depth` (h,w) metres, and keep them in
        memory (`path` None) or write them to `path`_rgb.npy / `path`_depth.npy."""
        rgb = (image * 255.0).round_().clamp_(0, 255).to(torch.uint8).cpu().numpy()
        steps = torch.round(depth / KEYFRAME_DEPTH_STEP)
        steps = torch.where((steps > 0) & (steps <= 65535), steps, torch.zeros_like(steps))
        d = steps.to(torch.int32).cpu().numpy().astype(np.uint16)
        if path is None:
            return cls(rgbd=(rgb, d), **fields)
        np.save(f"{path}_rgb.npy", rgb)
        np.save(f"{path}_depth.npy", d)
        return cls(path=path, **fields)

    def _arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if self.rgbd is not None:
            return self.rgbd
        return np.load(f"{self.path}_rgb.npy"), np.load(f"{self.path}_depth.npy")

    def load(self, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(image (h,w,3) float32 in [0,1], depth (h,w) float32 metres, 0 = invalid)."""
        rgb, d = self._arrays()
        image = torch.from_numpy(rgb).to(device=device, dtype=torch.float32) / 255.0
        depth = torch.from_numpy(d).to(device=device, dtype=torch.float32) * KEYFRAME_DEPTH_STEP
        return image, depth

    @property
    def depth(self) -> torch.Tensor:
        """(h,w) float32 metres, 0 = invalid."""
        return self.load(self.world_to_camera.device)[1]

    @property
    def nbytes(self) -> int:
        """Bytes of image data held in memory (0 when on disk)."""
        return sum(a.nbytes for a in self.rgbd) if self.rgbd is not None else 0


def resize_rgbd(rgb: np.ndarray, depth: np.ndarray, camera: Camera, scale: float, device=None):
    """(image (h,w,3) float32 in [0,1], depth (h,w) float32, camera) at `scale` of the frame's
    resolution: colour by area averaging, depth by averaging the valid pixels of each output
    pixel's area (0 where fewer than half of them are valid). Non-finite or negative depths
    count as invalid."""
    image = torch.as_tensor(np.asarray(rgb), device=device)
    image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    d = torch.as_tensor(np.asarray(depth, dtype=np.float32), device=device)
    d = torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d))  # NaN / inf / negative: invalid
    if scale == 1.0:
        return image, d, camera
    cam = camera.scaled(scale)
    size = (cam.height, cam.width)
    image = F.interpolate(image.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0).contiguous()
    valid = (d > 0).float()[None, None]
    num = F.interpolate(d[None, None] * valid, size=size, mode="area")[0, 0]
    den = F.interpolate(valid, size=size, mode="area")[0, 0]
    d = torch.where(den >= 0.5, num / den.clamp_min(1e-12), torch.zeros_like(num))
    return image, d, cam


class _Adam:
    """Adam over the map's parameter tensors with per-row moments and step counts, so rows can
    be appended and removed (as 3DGS's densification helpers do with torch's Adam state)."""

    def __init__(self, lrs: dict[str, float], eps: float, betas=(0.9, 0.999)):
        self.lrs, self.eps, self.betas = lrs, eps, betas
        self.m: dict[str, torch.Tensor] = {}
        self.v: dict[str, torch.Tensor] = {}
        self.steps = torch.zeros(0)

    def __len__(self) -> int:
        return int(self.steps.shape[0])

    def resize(self, params: dict[str, torch.Tensor]) -> None:
        """Append zero moments for rows beyond the current state (the map grew at its end)."""
        n_old = len(self)
        for name, p in params.items():
            if name not in self.m:
                self.m[name] = torch.zeros_like(p, requires_grad=False)
                self.v[name] = torch.zeros_like(p, requires_grad=False)
                continue
            extra = p.shape[0] - n_old
            if extra > 0:
                z = torch.zeros((extra,) + tuple(p.shape[1:]), dtype=p.dtype, device=p.device)
                self.m[name] = torch.cat([self.m[name], z])
                self.v[name] = torch.cat([self.v[name], z])
        n = next(iter(params.values())).shape[0]
        if n > n_old:
            self.steps = torch.cat([self.steps.to(next(iter(params.values())).device), torch.zeros(n - n_old)])

    def keep(self, mask: torch.Tensor) -> None:
        for d in (self.m, self.v):
            for name in d:
                d[name] = d[name][mask]
        self.steps = self.steps[mask]

    def reset(self) -> None:
        self.m, self.v, self.steps = {}, {}, torch.zeros(0)

    def zero_rows(self, name: str, rows: torch.Tensor | slice | None = None) -> None:
        """Forget the moments of parameter `name` (all rows or `rows`)."""
        if name in self.m:
            sel = slice(None) if rows is None else rows
            self.m[name][sel] = 0
            self.v[name][sel] = 0

    @torch.no_grad()
    def step(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> None:
        b1, b2 = self.betas
        self.steps += 1
        c1 = 1 - b1**self.steps  # (N,)
        c2 = 1 - b2**self.steps
        for name, p in params.items():
            g = grads.get(name)
            if g is None:
                continue
            m, v = self.m[name], self.v[name]
            m.mul_(b1).add_(g, alpha=1 - b1)
            v.mul_(b2).addcmul_(g, g, value=1 - b2)
            shape = (-1,) + (1,) * (p.dim() - 1)
            denom = (v / c2.view(shape)).sqrt_().add_(self.eps)
            p.sub_(self.lrs[name] * (m / c1.view(shape)) / denom)


class GaussianSplattingMapper(Mapper):
    """3DGS mapping of the shared GaussianMap from keyframe images (see the module docstring).

    `rasterizer` and `sampler` default to the ones the config names, built through the plugin
    registry; tests may pass their own.

    Threads (real-time mode): `add_keyframe` (tracking thread) and `optimize` (mapping thread)
    may run concurrently. Keyframe bookkeeping is append-only (a keyframe is stored before its
    id is published in `keyframe_ids` / `pending`); every change to the map and to the
    optimiser state happens under `gaussian_map.lock`, which a training step holds from render
    to update, so rows the core appends never arrive mid-step."""

    def __init__(self, cfg: GaussianSplattingConfig, rasterizer: Rasterizer | None = None, sampler=None):
        self.cfg = cfg
        if rasterizer is None:
            from slamkit.registry import create_rasterizer

            rasterizer = create_rasterizer(cfg.rasterizer)
        if sampler is None:
            from slamkit.registry import default_registry

            registry = default_registry()
            spec = registry.get("sampler", cfg.sampler)
            sampler = spec.cls(spec.config())
        self.rasterizer = rasterizer
        self.sampler = sampler
        try:
            params = inspect.signature(sampler.sample).parameters
            self._sampler_takes_poses = "keyframe_poses" in params or any(
                p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()
            )
        except (TypeError, ValueError):
            self._sampler_takes_poses = False
        self.rng = np.random.default_rng(cfg.seed)
        self.max_scale = cfg.max_scale if cfg.max_scale is not None else FALLBACK_MAX_SCALE
        self.keyframes: dict[int, Keyframe] = {}
        self.keyframe_ids: list[int] = []
        self.pending: deque[int] = deque()
        self.iteration = 0          # optimisation steps taken (skipped ones excluded)
        self.skipped_steps = 0      # steps skipped for a non-finite loss or gradient
        self.stale_steps = 0        # steps dropped: the optimiser state was rebuilt during them
        self._generation = 0        # bumped whenever the optimised leaf tensors are replaced
        self.last_loss: float | None = None
        self._adam = _Adam({n: getattr(cfg, f) for n, f in _LR_FIELDS.items()}, cfg.adam_eps)
        self._tensors: dict[str, torch.Tensor] = {}
        self._grad_accum = torch.zeros(0)
        self._grad_count = torch.zeros(0)
        self._filtered: set[int] = set()
        self.pruned_by_memory_guard = 0   # Gaussians removed by the max_gaussians guard
        self.memory_guard_prunings = 0    # times the guard pruned
        self._keyframe_dir: Path | None = None
        self.gaussian_map = GaussianMap()

    # -- the Mapper role -------------------------------------------------------------------
    def bind(self, gaussian_map: GaussianMap) -> None:
        self.gaussian_map = gaussian_map
        self._adam.reset()
        self._tensors = {}

    def select_new_gaussians(self, frame: Frame, result: TrackingResult) -> np.ndarray | None:
        """With skip_covered on: a bool mask over `result.gaussians`, False where the map
        already covers the Gaussian's pixel; None = keep all. (A hook for the core to call
        before the keyframe's Gaussians are added; `add_keyframe` applies the same rule to the
        rows just added when the core did not call it.)"""
        if not self.cfg.skip_covered or result.gaussians is None or len(result.gaussians) == 0:
            return None
        self._filtered.add(frame.index)
        with self.gaussian_map.lock:
            covered = self._covered(frame, result.pose, torch.as_tensor(result.gaussians.means, dtype=torch.float32),
                                    len(self.gaussian_map))
        return ~covered.cpu().numpy()

    def add_keyframe(self, frame: Frame, result: TrackingResult, kind: KeyframeKind, new_rows: slice) -> None:
        gm = self.gaussian_map
        if self.cfg.skip_covered and frame.index not in self._filtered and new_rows.stop > new_rows.start:
            with gm.lock:
                self._sync()
                covered = self._covered(frame, result.pose, gm.means.detach()[new_rows], new_rows.start)
                if covered.any():
                    keep = torch.ones(len(gm), dtype=torch.bool, device=gm.device)
                    keep[new_rows.start : new_rows.stop] = ~covered
                    self._keep(keep)
                    log.debug("keyframe at frame %d: %d of %d new Gaussians cover mapped pixels, dropped",
                              frame.index, int(covered.sum()), new_rows.stop - new_rows.start)
        self._filtered.discard(frame.index)
        if self.cfg.max_gaussians is not None and len(gm) > self.cfg.max_gaussians:
            with gm.lock:
                self._sync()
                self.enforce_max_gaussians(protect=slice(min(new_rows.start, len(gm)), len(gm)))
        image, depth, cam = resize_rgbd(frame.rgb, frame.depth, frame.camera, self.cfg.resolution_scale, gm.device)
        pose = np.asarray(result.pose, dtype=np.float64).copy()
        kf_id = len(self.keyframe_ids)
        kf = Keyframe.store(
            image, depth, self._keyframe_path(kf_id),
            id=kf_id,
            frame_index=frame.index,
            kind=kind,
            pose=pose,
            world_to_camera=torch.as_tensor(invert_pose(pose), dtype=torch.float32, device=gm.device),
            camera=cam,
        )
        self.keyframes[kf.id] = kf
        self.keyframe_ids.append(kf.id)
        self.pending.append(kf.id)

    def optimize(self, iterations: int) -> int:
        """Up to `iterations` steps: first the keyframes not yet trained on (one step each),
        then keyframes from the sampler. Returns the steps attempted (skipped ones included);
        0 while there is no keyframe or no Gaussian (e.g. a tracker that adds none), so a
        real-time mapping loop waits instead of spinning."""
        done = 0
        if len(self.gaussian_map) == 0:
            return 0
        while done < iterations and self.keyframe_ids:
            kf_id = self.pending.popleft() if self.pending else self._sample()
            self.train_step(self.keyframes[kf_id])
            done += 1
        return done

    def finish(self) -> None:
        if self.cfg.final_iterations:
            start = time.perf_counter()
            done = self.optimize(self.cfg.final_iterations)
            log.info("final mapping: %d steps in %.1f s", done, time.perf_counter() - start)
        if self.cfg.prune_every:
            with self.gaussian_map.lock:
                self._sync()
                self.prune()
        if self.memory_guard_prunings:
            log.info("memory guard (max_gaussians %d): %d Gaussians pruned in %d prunings", self.cfg.max_gaussians,
                     self.pruned_by_memory_guard, self.memory_guard_prunings)

    def _keyframe_path(self, kf_id: int) -> Path | None:
        """Where keyframe `kf_id`'s images go: None (memory) or a file prefix in the keyframe
        folder (keyframe_dir, else a temporary folder removed with the mapper)."""
        if self.cfg.keyframe_storage is not KeyframeStorage.disk:
            return None
        if self._keyframe_dir is None:
            if self.cfg.keyframe_dir is not None:
                self._keyframe_dir = Path(self.cfg.keyframe_dir)
                self._keyframe_dir.mkdir(parents=True, exist_ok=True)
            else:
                self._keyframe_dir = Path(tempfile.mkdtemp(prefix="slamkit-keyframes-"))
                weakref.finalize(self, shutil.rmtree, self._keyframe_dir, ignore_errors=True)
        return self._keyframe_dir / f"keyframe_{kf_id:06d}"

    def keyframe_memory_bytes(self) -> int:
        """Bytes of keyframe images held in memory (0 with keyframe_storage=disk)."""
        return sum(kf.nbytes for kf in self.keyframes.values())

    # -- training --------------------------------------------------------------------------
    def _sample(self) -> int:
        current = self.keyframes[self.keyframe_ids[-1]].pose
        if self._sampler_takes_poses:
            poses = {k: self.keyframes[k].pose for k in self.keyframe_ids}
            return self.sampler.sample(self.keyframe_ids, current, self.rng, keyframe_poses=poses)
        return self.sampler.sample(self.keyframe_ids, current, self.rng)

    def _sync(self) -> dict[str, torch.Tensor]:
        """Make the map's parameter tensors optimisable leaves and the Adam state match them.

        Rows are only ever removed by this mapper (which cuts the state itself); any other
        change of the map's tensors is the core appending rows at the end. Call under the lock."""
        gm = self.gaussian_map
        params = gm.parameters()
        n = len(gm)
        changed = any(self._tensors.get(k) is not t for k, t in params.items())
        if changed:
            if n < len(self._adam):
                log.warning("the Gaussian map lost rows outside the mapper; optimiser state reset")
                self._adam.reset()
                self._grad_accum = torch.zeros(0)
                self._grad_count = torch.zeros(0)
            for name, t in params.items():
                if not (t.is_leaf and t.requires_grad):
                    t = t.detach().requires_grad_(True)
                    setattr(gm, name, t)
                params[name] = t
            self._tensors = dict(params)
            self._generation += 1
        if n != len(self._adam) or not self._adam.m:
            self._adam.resize(params)
        if self.cfg.densify and len(self._grad_accum) != n:
            extra = n - len(self._grad_accum)
            self._grad_accum = torch.cat([self._grad_accum, torch.zeros(extra)])
            self._grad_count = torch.cat([self._grad_count, torch.zeros(extra)])
        return params

    def render(self, world_to_camera: torch.Tensor, camera: Camera, rows: int | None = None,
               params: dict[str, torch.Tensor] | None = None) -> RenderOutput:
        """Render the map (its first `rows` rows when given) with the mapper's rasteriser."""
        p = params if params is not None else self.gaussian_map.parameters()
        sl = slice(None) if rows is None else slice(0, rows)
        if p["means"][sl].shape[0] == 0:
            z = torch.zeros((camera.height, camera.width), device=self.gaussian_map.device)
            return RenderOutput(torch.zeros(camera.height, camera.width, 3, device=z.device), z, z.clone())
        return self.rasterizer.render(
            p["means"][sl],
            p["quats"][sl],
            torch.exp(p["log_scales"][sl]),
            torch.sigmoid(p["opacity_logits"][sl]),
            p["colors"][sl],
            world_to_camera,
            camera,
        )

    def render_view(self, pose: np.ndarray, camera: Camera) -> RenderOutput:
        """The map from `pose` (camera-to-world) with the mapper's rasteriser, no gradients (viewers)."""
        return render_map(self.rasterizer, self.gaussian_map, pose, camera)

    def loss(self, out: RenderOutput, kf: Keyframe) -> torch.Tensor:
        """0.8 L1(rgb) + 0.2 (1 - SSIM) + 0.1 L1(depth / 10) over the pixels with valid depth
        (all pixels for the colour terms when none has depth)."""
        cfg = self.cfg
        image, depth = kf.load(out.color.device)
        mask = depth > 0
        has_depth = bool(mask.any())
        if not has_depth:
            mask = torch.ones_like(mask)
        m = mask.to(out.color.dtype)
        n = m.sum()
        l1 = ((out.color - image).abs() * m[..., None]).sum() / (3 * n)
        loss = cfg.weight_l1 * l1
        if cfg.weight_ssim:
            s = image_metrics.ssim(out.color, image, mask, differentiable=True)
            loss = loss + cfg.weight_ssim * (1 - s)
        if cfg.weight_depth and has_depth:
            ld = ((out.depth - depth).abs() * m).sum() / n / DEPTH_UNIT
            loss = loss + cfg.weight_depth * ld
        return loss

    def train_step(self, kf: Keyframe) -> bool:
        """One optimisation step on keyframe `kf`; False when it was skipped (empty map, a
        non-finite loss or gradient, or the optimiser state changed under it).

        The lock is held while the parameters are taken and while the update is applied, not
        while rendering and differentiating (most of the step), so that in real-time mode the
        tracking thread can add a keyframe's Gaussians meanwhile. Those are rows appended at the
        end (a new tensor): the step updates its own rows and copies them into the new tensors.
        If the optimiser state was rebuilt meanwhile (a keyframe that pruned or filtered rows),
        the step is dropped and counted in `stale_steps`."""
        gm = self.gaussian_map
        with gm.lock:
            params = self._sync()
            n, generation = len(gm), self._generation
        if n == 0:
            return False
        out = self.render(kf.world_to_camera, kf.camera, params=params)
        loss = self.loss(out, kf)
        if not bool(torch.isfinite(loss)):
            with gm.lock:
                return self._skip(f"loss {float(loss.detach())}")
        names = list(params)
        grads = torch.autograd.grad(loss, [params[k] for k in names], allow_unused=True)
        grads = {k: g for k, g in zip(names, grads) if g is not None}
        if not all(bool(torch.isfinite(g).all()) for g in grads.values()):
            with gm.lock:
                return self._skip("non-finite gradient")
        with gm.lock:
            if self._generation != generation:
                self.stale_steps += 1
                return False
            self.last_loss = float(loss.detach())
            if self.cfg.densify and "means" in grads:
                self._accumulate_view_gradient(grads["means"], kf)
            self._adam.step(params, grads)
            with torch.no_grad():
                params["colors"].clamp_(0.0, 1.0)
                for name, t in params.items():  # rows appended meanwhile live in new tensors
                    live = getattr(gm, name)
                    if live is not t:
                        live[:n] = t.detach()
            gm.version += 1
            self.iteration += 1
            it = self.iteration
            if self.cfg.densify and it % self.cfg.densify_every == 0:
                self.densify_and_prune()
            elif self.cfg.prune_every and it % self.cfg.prune_every == 0:
                self.prune()
            if self.cfg.opacity_reset and it % self.cfg.opacity_reset_every == 0:
                self.reset_opacity()
        return True

    def _skip(self, why: str) -> bool:
        """Skip a step (parameters and moments unchanged), removing at once the Gaussians whose
        parameters are not finite (they would make every later step on their views fail)."""
        self.skipped_steps += 1
        gm = self.gaussian_map
        with torch.no_grad():
            finite = torch.ones(len(gm), dtype=torch.bool, device=gm.device)
            for t in gm.parameters().values():
                finite &= torch.isfinite(t.detach()).reshape(len(gm), -1).all(dim=1)
        dropped = int((~finite).sum())
        if dropped:
            self._keep(finite)
        if self.skipped_steps <= 5 or self.skipped_steps % 100 == 0:
            extra = f"; removed {dropped} Gaussians with non-finite parameters" if dropped else ""
            log.warning("mapping step skipped (%s)%s; %d skipped so far", why, extra, self.skipped_steps)
        return False

    # -- structure: pruning, densification, opacity reset (under the lock) ------------------
    def _keep(self, mask: torch.Tensor) -> None:
        """Remove the rows where `mask` is False from the map and from the optimiser state."""
        gm = self.gaussian_map
        gm.keep(mask)
        self._adam.keep(mask)
        if len(self._grad_accum) == len(mask):
            self._grad_accum = self._grad_accum[mask]
            self._grad_count = self._grad_count[mask]
        self._tensors = {}
        self._sync()

    def prune_mask(self) -> torch.Tensor:
        """True for the Gaussians to keep: opacity >= prune_min_opacity, largest scale <=
        max_scale, every parameter finite."""
        gm = self.gaussian_map
        with torch.no_grad():
            keep = gm.opacities.detach() >= self.cfg.prune_min_opacity
            keep &= gm.scales.detach().max(dim=1).values <= self.max_scale
            for t in gm.parameters().values():
                keep &= torch.isfinite(t.detach()).reshape(len(gm), -1).all(dim=1)
        return keep

    def prune(self) -> int:
        """Prune now; returns the number of Gaussians removed."""
        keep = self.prune_mask()
        removed = int((~keep).sum())
        if removed:
            self._keep(keep)
            log.debug("pruned %d Gaussians, %d left", removed, len(self.gaussian_map))
        return removed

    def enforce_max_gaussians(self, protect: slice | None = None) -> int:
        """The memory guard: when the map holds more than `max_gaussians` Gaussians, remove the
        least opaque ones (lowest opacity logit, i.e. sigmoid opacity; ties: the older rows
        first) until floor((1 - memory_guard_margin) max_gaussians) remain. Rows in `protect`
        (a keyframe's Gaussians just added, at their initial opacity) go only when the others
        do not make room. Removal is `_keep`, as pruning: map, Adam moments and densification
        statistics stay aligned, the map's version changes. Call under the lock after `_sync`.
        Returns the number removed."""
        cap, gm = self.cfg.max_gaussians, self.gaussian_map
        n = len(gm)
        if cap is None or n <= cap:
            return 0
        excess = n - max(1, int(cap * (1.0 - self.cfg.memory_guard_margin)))
        with torch.no_grad():
            key = torch.nan_to_num(gm.opacity_logits.detach().clone(), nan=-math.inf)
            if protect is not None:
                key[protect] = math.inf
            drop = torch.sort(key, stable=True).indices[:excess]
            keep = torch.ones(n, dtype=torch.bool, device=gm.device)
            keep[drop] = False
        self._keep(keep)
        self.pruned_by_memory_guard += excess
        self.memory_guard_prunings += 1
        log.debug("memory guard: pruned the %d least opaque Gaussians, %d left", excess, len(gm))
        return excess

    def _accumulate_view_gradient(self, grad_means: torch.Tensor, kf: Keyframe) -> None:
        """3DGS's densification statistic, the norm of the gradient with respect to the
        projected mean in NDC units, approximated from the 3D gradient: |dL/d(x,y)_cam| * z * W
        / (2 fx). Counted for the Gaussians with a non-zero gradient (visible)."""
        gm = self.gaussian_map
        W = kf.world_to_camera
        with torch.no_grad():
            z = gm.means.detach() @ W[2, :3] + W[2, 3]
            g_cam = grad_means @ W[:3, :3].T
            g = g_cam[:, :2].norm(dim=1) * z.clamp_min(0) * kf.camera.width / (2 * kf.camera.fx)
            visible = (grad_means != 0).any(dim=1) & (z > 0.01)
            self._grad_accum[visible] += g[visible]
            self._grad_count[visible] += 1

    def densify_and_prune(self) -> None:
        """3DGS clone / split of Gaussians with a large average view-space gradient, then
        pruning."""
        gm = self.gaussian_map
        cfg = self.cfg
        with torch.no_grad():
            avg = self._grad_accum / self._grad_count.clamp_min(1)
            selected = avg >= cfg.densify_grad_threshold
            room = cfg.densify_max_gaussians - len(gm)
            if room <= 0:
                selected[:] = False
            elif int(selected.sum()) > room // 2:
                # keep the largest gradients within the budget (a split adds two rows)
                idx = torch.nonzero(selected).squeeze(1)
                top = idx[torch.argsort(avg[idx], descending=True)[: room // 2]]
                selected = torch.zeros_like(selected)
                selected[top] = True
            max_s = gm.scales.detach().max(dim=1).values
            clone = selected & (max_s <= cfg.densify_scale_threshold)
            split = selected & ~clone
            n0 = len(gm)
            new = []
            if clone.any():
                new.append(self._rows_numpy(clone))
            if split.any():
                src = self._rows_numpy(split)
                R = quat_to_rotmat(gm.quats.detach()[split]).numpy()
                s = np.exp(src["log_scales"])
                for _ in range(2):
                    child = dict(src)
                    offset = np.einsum("nij,nj->ni", R, s * self.rng.standard_normal(s.shape))
                    child["means"] = src["means"] + offset
                    child["log_scales"] = np.log(s / 1.6)
                    new.append(child)
            for rows in new:
                self._append_rows(rows)
            self._grad_accum.zero_()
            self._grad_count.zero_()
            self._sync()
            if split.any():
                keep = torch.ones(len(gm), dtype=torch.bool)
                keep[:n0][split] = False
                self._keep(keep)
        self.prune()
        self.enforce_max_gaussians()

    def _rows_numpy(self, mask: torch.Tensor) -> dict[str, np.ndarray]:
        gm = self.gaussian_map
        out = {k: t.detach()[mask].cpu().numpy().copy() for k, t in gm.parameters().items()}
        out["trackable"] = gm.trackable[mask].cpu().numpy()
        out["keyframe_id"] = gm.keyframe_id[mask].cpu().numpy()
        return out

    def _append_rows(self, rows: dict[str, np.ndarray]) -> None:
        gm = self.gaussian_map
        opacity = 1.0 / (1.0 + np.exp(-rows["opacity_logits"].astype(np.float64)))
        opacity = np.clip(opacity, 1e-6, 1 - 1e-6)
        new = gm.append(rows["means"], rows["quats"], np.exp(rows["log_scales"]), rows["colors"], opacity,
                        rows["trackable"], -1)
        gm.keyframe_id[new] = torch.as_tensor(rows["keyframe_id"], device=gm.device)

    def reset_opacity(self) -> None:
        """3DGS opacity reset: opacities above 0.01 become 0.01; their moments are forgotten."""
        gm = self.gaussian_map
        with torch.no_grad():
            gm.opacity_logits.clamp_(max=math.log(0.01 / 0.99))
        self._adam.zero_rows("opacity_logits")
        gm.version += 1

    # -- map growth control ------------------------------------------------------------------
    def _covered(self, frame: Frame, pose: np.ndarray, means: torch.Tensor, rows: int) -> torch.Tensor:
        """(M,) bool: the world points `means` whose pixel in `frame`'s view at `pose` the first
        `rows` map rows already cover (alpha > covered_alpha, expected depth within
        covered_depth_tolerance of the point's depth). Call under the lock."""
        cam = frame.camera.scaled(self.cfg.resolution_scale) if self.cfg.resolution_scale != 1 else frame.camera
        m = len(means)
        covered = torch.zeros(m, dtype=torch.bool)
        if rows == 0 or m == 0:
            return covered
        w2c = torch.as_tensor(invert_pose(np.asarray(pose, dtype=np.float64)), dtype=torch.float32)
        with torch.no_grad():
            out = self.render(w2c, cam, rows=rows)
            pc = means.float() @ w2c[:3, :3].T + w2c[:3, 3]
            z = pc[:, 2]
            ok = z > 1e-6
            zs = torch.where(ok, z, torch.ones_like(z))
            u = torch.round(cam.fx * pc[:, 0] / zs + cam.cx).long()
            v = torch.round(cam.fy * pc[:, 1] / zs + cam.cy).long()
            ok &= (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            ui, vi = u[ok], v[ok]
            alpha = out.alpha[vi, ui]
            depth = out.depth[vi, ui] / alpha.clamp_min(1e-6)
            covered[ok] = (alpha > self.cfg.covered_alpha) & ((depth - z[ok]).abs() < self.cfg.covered_depth_tolerance)
        return covered

    # -- evaluation --------------------------------------------------------------------------
    def evaluate(self, dataset, poses: list[np.ndarray], out_dir) -> dict[str, Any]:
        """Render every eval_every-th frame from its estimated pose; PSNR / SSIM (masked by
        valid depth) for keyframes, other frames and all; depth L1 in cm; images and map.ply
        into `out_dir` (skipped when None)."""
        from slamkit.ply import save_ply

        cfg = self.cfg
        gm = self.gaussian_map
        n = min(len(dataset), len(poses))
        indices = list(range(0, n, cfg.eval_every))
        train_frames = {kf.frame_index for kf in self.keyframes.values()}
        n_img = min(cfg.save_images, len(indices))
        save_at = set(np.linspace(0, len(indices) - 1, n_img).round().astype(int).tolist()) if n_img else set()
        out_dir = Path(out_dir) if out_dir is not None else None
        rows = {"all": [], "train": [], "test": []}
        depth_l1 = []
        start = time.perf_counter()
        for k, i in enumerate(indices):
            frame = dataset[i]
            image, depth, cam = resize_rgbd(frame.rgb, frame.depth, frame.camera, cfg.eval_resolution_scale, gm.device)
            w2c = torch.as_tensor(invert_pose(np.asarray(poses[i], dtype=np.float64)), dtype=torch.float32,
                                  device=gm.device)
            with gm.lock, torch.no_grad():
                out = self.render(w2c, cam)
            color = out.color.clamp(0, 1)
            mask = depth > 0
            p = image_metrics.psnr(color, image, mask)
            s = image_metrics.ssim(color, image, mask)
            depth_l1.append(image_metrics.l1_depth(out.depth, depth, mask))
            rows["all"].append((p, s))
            rows["train" if frame.index in train_frames else "test"].append((p, s))
            if out_dir is not None and k in save_at:
                _save_side_by_side(out_dir / f"render_{i:04d}.png", color, image)
        elapsed = time.perf_counter() - start

        def mean(values):
            values = [v for v in values if math.isfinite(v)]
            return float(np.mean(values)) if values else None

        metrics: dict[str, Any] = {}
        for group, key in (("all", ""), ("train", "_train"), ("test", "_test")):
            metrics[f"psnr{key}"] = mean([p for p, _ in rows[group]])
            metrics[f"ssim{key}"] = mean([s for _, s in rows[group]])
        l1 = mean(depth_l1)
        metrics.update(
            depth_l1_cm=None if l1 is None else 100.0 * l1,
            num_gaussians=len(gm),
            eval_frames=len(indices),
            eval_train_frames=len(rows["train"]),
            eval_time_s=elapsed,
            mapping_steps=self.iteration,
            mapping_skipped_steps=self.skipped_steps,
            mapping_stale_steps=self.stale_steps,
            pruned_by_memory_guard=self.pruned_by_memory_guard,
            memory_guard_prunings=self.memory_guard_prunings,
            keyframe_memory_mb=self.keyframe_memory_bytes() / 2**20,
            train_resolution=[self.keyframes[self.keyframe_ids[0]].camera.width,
                              self.keyframes[self.keyframe_ids[0]].camera.height] if self.keyframe_ids else None,
        )
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            save_ply(out_dir / "map.ply", gm)
        return metrics


def _save_side_by_side(path: Path, render: torch.Tensor, truth: torch.Tensor) -> None:
    from PIL import Image

    both = torch.cat([render, truth], dim=1).clamp(0, 1)
    Image.fromarray((both.cpu().numpy() * 255 + 0.5).astype(np.uint8)).save(path)


@hookimpl
def slamkit_mappers():
    return [PluginSpec("gaussian_splatting", GaussianSplattingMapper, GaussianSplattingConfig)]
