"""`mapper=gaussian_splatting`: 3D Gaussian Splatting training of the shared map (paper Sec. 3.2).

The mapper is a trainer composed of parts, each a plugin chosen and configured on the command
line: the rasteriser (`rasterizer=`), the training-view sampler (`sampler=`), the densification
strategy (`strategy=`), the optimiser (`optimizer=`) and the loss (`loss=`). It owns the
keyframes and the training loop; the map's parameters are the GaussianMap's own leaf tensors
(the tracker's next target is taken from the values it optimised: that exchange is the method),
the optimiser owns its per-row state, and the strategy edits rows only through the shared row
operations (`slamkit.map.editing.MapEdit`).

A training step, as in 3DGS: take a keyframe (the ones not yet trained on first, once each, then
the sampler's choice), render it, the loss, its gradient, the optimiser's update, then the
strategy's post-backward hook (statistics, densification, pruning on its schedule).

Threads (real-time mode): `admit` and `add_keyframe` (tracking thread) may run beside
`optimize` (mapping thread). A step holds the map's lock only to take the parameters and to
apply its update, not while rendering and differentiating, so a keyframe's Gaussians can be
appended meanwhile (the step then gives them no gradient); a step during which rows were
removed or overwritten is dropped (`stale_steps`).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

from slamkit.formats.ply import save_ply
from slamkit.map.gaussian_map import GaussianMap
from slamkit.geometry.transforms import invert_pose
from slamkit.map.editing import MapEdit
from slamkit.map.rendering import RenderOutput, render_map
from slamkit.roles import (DensifyStrategy, KeyframeSampler, KeyframeView, Mapper, MapOptimizer, MappingLoss,
                           Rasterizer, StepInfo, TrainingView)
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.config import GaussianSplattingConfig
from slamkit_plugins.mappers.gaussian_splatting.evaluation import evaluate_renders
from slamkit_plugins.mappers.gaussian_splatting.keyframes import KeyframeStore
from slamkit_plugins.mappers.gaussian_splatting.timing import PhaseTimer

log = logging.getLogger(__name__)

#: Pixels: a training window's smallest side (the loss's SSIM takes 11x11 windows; a tile is 16).
MIN_WINDOW_SIDE = 16


class GaussianSplattingMapper(Mapper):
    """3DGS mapping of the shared GaussianMap from keyframe images (see the module docstring)."""

    parts = ("rasterizer", "sampler", "strategy", "optimizer", "loss")

    def __init__(self, cfg: GaussianSplattingConfig, rasterizer: Rasterizer, sampler: KeyframeSampler,
                 strategy: DensifyStrategy, optimizer: MapOptimizer, loss: MappingLoss):
        self.cfg = cfg
        self.rasterizer, self.sampler, self.strategy, self.optimizer, self.loss = (
            rasterizer, sampler, strategy, optimizer, loss)
        self.keyframes = KeyframeStore(cfg.training_scale(realtime=False), cfg.keyframe_storage, cfg.keyframe_dir,
                                       cfg.view_cache_mb)
        self.pending: deque[int] = deque()  # keyframes not trained on yet
        self.trained: dict[int, int] = {}  # steps taken on each keyframe
        self.rng = np.random.default_rng(cfg.seed)
        self.steps = 0  # training steps taken (skipped and dropped ones excluded)
        self.skipped_steps = 0  # steps skipped for a non-finite loss or gradient
        self.stale_steps = 0  # steps dropped: rows were removed or overwritten during them
        # Seconds in optimize() and the strategy's finish (final steps included): wall clock, and
        # CPU time of the calling thread (all of the work with OMP_NUM_THREADS=1, whatever the load).
        self.train_time_s = 0.0
        self.train_cpu_s = 0.0
        self.last_loss: float | None = None
        self.timer = PhaseTimer()  # where the steps' time goes (metrics.json: mapping_step_ms)
        self.bind(GaussianMap())

    def use_mode(self, realtime: bool) -> None:
        self.keyframes.resolution_scale = self.cfg.training_scale(realtime)

    def bind(self, gaussian_map: GaussianMap) -> None:
        self.gaussian_map = gaussian_map
        self.timer.sync = torch.cuda.synchronize if gaussian_map.device.type == "cuda" else None
        self.optimizer.reset()
        self.edit = MapEdit(gaussian_map, self.optimizer, self.strategy.state)

    # -- the Mapper role ---------------------------------------------------------------------
    def admit(self, frame, pose, new):
        camera = self.keyframes.training_camera(frame.camera)
        w2c = torch.as_tensor(invert_pose(np.asarray(pose, dtype=np.float64)), dtype=torch.float32,
                              device=self.gaussian_map.device)
        view = KeyframeView(camera, w2c, lambda: self.render(w2c, camera), input_camera=frame.camera,
                            centres=self.gaussian_map.means.detach())
        return self.strategy.admit(new, view)

    def add_keyframe(self, frame, result, kind, new_rows) -> None:
        keyframe = self.keyframes.add(frame, result.pose, kind)
        self.pending.append(keyframe.id)
        with self.gaussian_map.lock:
            self.strategy.after_keyframe(self.edit, new_rows)

    def optimize(self, iterations: int) -> int:
        """Up to `iterations` steps; returns the steps attempted (skipped and dropped ones
        included); 0 while there is no keyframe or no Gaussian, so a real-time mapping loop
        waits instead of spinning."""
        start, cpu_start, done = time.perf_counter(), time.thread_time(), 0
        while done < iterations and len(self.keyframes) and len(self.gaussian_map):
            with self.timer("view"):
                kf_id = self.pending.popleft() if self.pending else self._sample()
                coarse = self.trained.get(kf_id, 0) < self.cfg.coarse_steps
                self.trained[kf_id] = self.trained.get(kf_id, 0) + 1
                view = self._window(self.keyframes.view(kf_id, self.gaussian_map.device, 0.5 if coarse else 1.0))
            self.train_step(view)
            self.timer.steps += 1
            done += 1
        self._count_time(start, cpu_start)
        return done

    def finish(self) -> None:
        start, cpu_start = time.perf_counter(), time.thread_time()
        with self.gaussian_map.lock:
            self.edit.sync()
            self.strategy.finish(self.edit)
        self._count_time(start, cpu_start)
        stats = self.strategy.metrics()
        if stats.get("memory_guard_prunings"):
            log.info("memory guard (max_gaussians %s): %d Gaussians pruned in %d prunings",
                     self.strategy.cfg.max_gaussians, stats["pruned_by_memory_guard"], stats["memory_guard_prunings"])

    def state_dict(self) -> dict[str, Any]:
        """Keyframes, the training schedule (pending, steps per keyframe, the sampler's random
        state), counters, the optimiser's and the strategy's state."""
        with self.gaussian_map.lock:  # copies (C calls) of what a mapping thread changes outside the lock
            pending, trained = self.pending.copy(), dict(self.trained)
            return {"keyframes": self.keyframes.state_dict(), "pending": list(pending),
                    "trained": [[k, v] for k, v in trained.items()], "rng": self.rng.bit_generator.state,
                    "steps": self.steps, "skipped_steps": self.skipped_steps, "stale_steps": self.stale_steps,
                    "train_time_s": self.train_time_s, "train_cpu_s": self.train_cpu_s, "last_loss": self.last_loss,
                    "optimizer": self.optimizer.state_dict(), "strategy": self.strategy.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        configured = self.keyframes.resolution_scale
        self.keyframes.load_state_dict(state["keyframes"])
        if self.keyframes.resolution_scale != configured:
            log.warning("resumed keyframes train at %g of the frame size, so new ones do too (not %g)",
                        self.keyframes.resolution_scale, configured)
        self.pending = deque(int(k) for k in state["pending"])
        self.trained = {int(k): int(v) for k, v in state["trained"]}
        self.rng.bit_generator.state = state["rng"]
        self.steps, self.skipped_steps, self.stale_steps = (int(state[k]) for k in ("steps", "skipped_steps",
                                                                                     "stale_steps"))
        self.train_time_s, self.train_cpu_s = float(state["train_time_s"]), float(state["train_cpu_s"])
        self.last_loss = state["last_loss"]
        device = self.gaussian_map.device
        self.optimizer.load_state_dict(state["optimizer"])
        self.optimizer.edit_rows(lambda name, v: v.to(device))
        self.strategy.load_state_dict(state["strategy"])

    def render_view(self, pose: np.ndarray, camera: Camera) -> RenderOutput:
        """The map from `pose` (camera-to-world) with the mapper's rasteriser, no gradients."""
        return render_map(self.rasterizer, self.gaussian_map, pose, camera)

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
                                   cfg.eval_every, cfg.eval_resolution_scale, cfg.save_images, out_dir)
        first = self.keyframes[self.keyframes.ids[0]].camera if len(self.keyframes) else None
        metrics.update(self.strategy.metrics(), mapping_steps=self.steps, mapping_skipped_steps=self.skipped_steps,
                       mapping_stale_steps=self.stale_steps, mapping_step_ms=self.timer.per_step_ms(),
                       mapping_train_time_s=self.train_time_s, mapping_train_cpu_s=self.train_cpu_s,
                       keyframe_memory_mb=self.keyframes.memory_bytes() / 2**20,
                       train_resolution=[first.width, first.height] if first else None)
        return metrics

    # -- training ----------------------------------------------------------------------------
    def _count_time(self, start: float, cpu_start: float) -> None:
        self.train_time_s += time.perf_counter() - start
        self.train_cpu_s += time.thread_time() - cpu_start

    def _window(self, view: TrainingView) -> TrainingView:
        """A random window of `view` of the configured size (`window`, at least MIN_WINDOW_SIDE
        pixels a side), or the view itself. A window may start up to its size (less
        MIN_WINDOW_SIDE) before the view's edge and is clipped to the view, so border pixels are
        trained about as often as the others (a window drawn inside the view would rarely hold
        them)."""
        if self.cfg.window >= 1.0:
            return view
        spans = []
        for size in (view.camera.width, view.camera.height):
            part = min(size, max(MIN_WINDOW_SIDE, round(size * self.cfg.window)))
            reach = part - MIN_WINDOW_SIDE if part < size else 0
            start = int(self.rng.integers(-reach, size - part + reach + 1))
            spans.append((max(start, 0), min(start + part, size) - max(start, 0)))
        (x0, width), (y0, height) = spans
        return view.window(x0, y0, width, height)

    def _sample(self) -> int:
        ids = list(self.keyframes.ids)
        poses = {k: self.keyframes[k].pose for k in ids}
        return self.sampler.sample(ids, poses[ids[-1]], self.rng, poses)

    def render(self, world_to_camera: torch.Tensor, camera: Camera,
               params: dict[str, torch.Tensor] | None = None) -> RenderOutput:
        """Render the map (or `params`, the map's parameters taken earlier) differentiably."""
        p = params if params is not None else self.gaussian_map.parameters()
        return self.rasterizer.render(p["means"], p["quats"], torch.exp(p["log_scales"]),
                                      torch.sigmoid(p["opacity_logits"]), p["colors"], world_to_camera, camera)

    def train_step(self, view: TrainingView) -> bool:
        """One optimisation step on `view`; False when it was skipped (empty map, a non-finite
        loss or gradient) or dropped (rows removed during it)."""
        gm, timer = self.gaussian_map, self.timer
        with self._locked():
            params, rows, structure = gm.parameters(), len(gm), gm.structure_version
        if rows == 0:
            return False
        with timer("render"):
            render = self.render(view.world_to_camera, view.camera, params)
        with timer("loss"):
            loss = self.loss(render, view)
        with timer("backward"):
            grads, problem = _gradients(loss, params)
        with self._locked():
            if problem:
                return self._skip(problem)
            if gm.structure_version != structure:
                self.stale_steps += 1
                return False
            with timer("optimizer"):
                live = gm.parameters()  # rows appended during the step had no part in it
                grads = {k: _pad_rows(g, len(gm)) for k, g in grads.items()}
                self.edit.sync()
                self.optimizer.step(live, grads)
                with torch.no_grad():
                    live["colors"].clamp_(0.0, 1.0)
                gm.version += 1
            self.steps += 1
            self.last_loss = float(loss.detach())
            with timer("strategy"):
                self.strategy.step_post_backward(self.edit, StepInfo(self.steps, view, render, grads, self.last_loss))
        return True

    @contextmanager
    def _locked(self):
        """Hold the map's lock; the wait counts as the step's `lock` phase."""
        with self.timer("lock"):
            self.gaussian_map.lock.acquire()
        try:
            yield
        finally:
            self.gaussian_map.lock.release()

    def _skip(self, why: str) -> bool:
        """Skip a step (parameters and moments unchanged), removing at once the Gaussians whose
        parameters are not finite (they would make every later step on their views fail).
        Call under the lock."""
        self.skipped_steps += 1
        params = self.edit.params
        finite = torch.ones(len(self.edit), dtype=torch.bool, device=self.gaussian_map.device)
        for t in params.values():
            finite &= torch.isfinite(t).reshape(len(t), -1).all(dim=1)
        dropped = self.edit.remove(~finite)
        if self.skipped_steps <= 5 or self.skipped_steps % 100 == 0:
            extra = f"; removed {dropped} Gaussians with non-finite parameters" if dropped else ""
            log.warning("mapping step skipped (%s)%s; %d skipped so far", why, extra, self.skipped_steps)
        return False


def _gradients(loss: torch.Tensor, params: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], str | None]:
    """The loss's gradient with respect to each parameter that has one, and what made the step
    unusable (a non-finite loss or gradient), else None."""
    if not bool(torch.isfinite(loss)):
        return {}, f"loss {float(loss.detach())}"
    names = list(params)
    grads = torch.autograd.grad(loss, [params[k] for k in names], allow_unused=True)
    grads = {k: g for k, g in zip(names, grads) if g is not None}
    # one reduction per tensor instead of a mask: a sum is finite iff every entry is (up to an
    # overflow, ~1e38, where skipping the step is right too)
    if grads and not bool(torch.isfinite(torch.stack([g.sum() for g in grads.values()])).all()):
        return grads, "non-finite gradient"
    return grads, None


def _pad_rows(g: torch.Tensor, rows: int) -> torch.Tensor:
    """`g` with zero rows appended up to `rows` rows."""
    extra = rows - g.shape[0]
    return g if extra <= 0 else torch.cat([g, g.new_zeros((extra,) + tuple(g.shape[1:]))])
