"""3D Gaussian Splatting training of the shared map from keyframes: the loop, composed of its
parts (rasteriser, training-view sampler, loss, optimiser, strategy).

The parameters are the GaussianMap's own leaf tensors, so the tracker's next target is taken
from the values the optimiser moved (GS-ICP SLAM's exchange); the optimiser owns its per-row
state and the strategy edits rows only through `MapEdit`, which keeps every per-row state
aligned. A step, as in 3DGS: take a keyframe (the untrained ones first, once each, then the
sampler's choice), render it, the loss, its gradient, the optimiser's update, the strategy's hook.
A loop closure's correction moves the Gaussians, the optimiser's state and the keyframes' poses
together (`move_keyframes`).

Threads (real time): `admit` (tracking thread, or the keyframe handover's for a mapping-only
keyframe) and `add_keyframe` (the keyframe handover's thread) may run beside `train` (mapping
thread), one keyframe at a time. A step holds the map's lock only to take the parameters and to apply its update, so a
keyframe's Gaussians can be appended meanwhile (the step gives them no gradient); a step during
which rows were removed or overwritten is dropped (`stale_steps`).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from slamkit.config import PluginConfig, RunContext, method_setting, require
from slamkit.geometry.transforms import invert_pose
from slamkit.map.gaussian_map import GaussianRows
from slamkit.roles.loss import MappingLoss
from slamkit.roles.map_edit import MapEdit
from slamkit.roles.mapping import Mapper
from slamkit.roles.optimizer import MapOptimizer
from slamkit.roles.rendering import Rasterizer, RenderOutput, render_map
from slamkit.roles.sampler import KeyframeSampler
from slamkit.roles.strategy import StepInfo, Strategy
from slamkit.roles.training_view import TrainingView
from slamkit.types import Camera, Frame, KeyframeKind
from slamkit_plugins.mappers.gaussian_splatting.admission import Admission, AdmissionConfig, KeyframeView
from slamkit_plugins.mappers.gaussian_splatting.keyframes import KeyframeStorage, KeyframeStore
from slamkit_plugins.mappers.gaussian_splatting.memory_cap import MemoryCap, MemoryCapConfig
from slamkit_plugins.mappers.gaussian_splatting.schedule import TrainingSchedule
from slamkit_plugins.mappers.gaussian_splatting.timing import PhaseTimer

log = logging.getLogger(__name__)

#: `resolution_scale` when null, by mode (real time trains at a quarter: twice the steps a keyframe).
SEQUENTIAL_RESOLUTION_SCALE = 0.5
REALTIME_RESOLUTION_SCALE = 0.25


@dataclass
class TrainerConfig(PluginConfig):
    """How the trainer trains (its parts have configs of their own)."""

    #: training images are the keyframes resized by this factor (null: 0.5, and 0.25 in real time)
    resolution_scale: float | None = method_setting(None)
    #: a keyframe's first steps (this many) see it at half the training resolution (0: off, the paper's)
    coarse_steps: int = 0
    #: a step trains on a random window of this fraction of the view's width and height (1: the whole view)
    window: float = 1.0
    #: memory | disk: where keyframe training images live (disk: .npy files read back when used)
    keyframe_storage: KeyframeStorage = KeyframeStorage.memory
    #: folder for keyframe_storage=disk (null: a temporary folder removed with the mapper)
    keyframe_dir: str | None = None
    #: MiB of training views kept between steps as float tensors, least recently used dropped first (0: off)
    view_cache_mb: float = 64.0
    #: the seed of the training-view draws and windows
    seed: int = 0
    #: which of a keyframe's Gaussians enter the map
    admission: AdmissionConfig = field(default_factory=AdmissionConfig)
    #: a bound on the map's size
    memory_cap: MemoryCapConfig = field(default_factory=MemoryCapConfig)

    def validate(self) -> None:
        require(self.resolution_scale is None or 0 < self.resolution_scale <= 1, "mapper.resolution_scale",
                "null or in (0, 1]", self.resolution_scale)
        require(0 < self.window <= 1, "mapper.window", "in (0, 1]", self.window)
        require(self.coarse_steps >= 0, "mapper.coarse_steps", "an integer >= 0 (0 = off)", self.coarse_steps)
        require(self.view_cache_mb >= 0, "mapper.view_cache_mb", "a size in MiB >= 0 (0 = off)", self.view_cache_mb)
        require(self.seed >= 0, "mapper.seed", "an integer >= 0 (numpy's generator seed)", self.seed)

    def resolve(self, context: RunContext) -> TrainerConfig:
        scale = REALTIME_RESOLUTION_SCALE if context.realtime else SEQUENTIAL_RESOLUTION_SCALE
        return self.fill_nulls(resolution_scale=scale)


class Trainer(Mapper):
    """A mapper that trains the shared map (`context.gaussian_map`) from keyframes with the given
    parts (see the module docstring); `GaussianSplattingMapper` adds its outputs."""

    def __init__(self, cfg: TrainerConfig, context: RunContext = RunContext(), *, rasterizer: Rasterizer,
                 sampler: KeyframeSampler, strategy: Strategy, optimizer: MapOptimizer, loss: MappingLoss):
        require(cfg.resolution_scale is not None, "mapper.resolution_scale",
                "a value (TrainerConfig.resolve fills it)", None)
        super().__init__(cfg, context)
        gaussian_map = self.gaussian_map
        self.rasterizer, self.sampler, self.strategy, self.optimizer, self.loss = (
            rasterizer, sampler, strategy, optimizer, loss)
        self.admission = Admission(cfg.admission)
        self.memory_cap = MemoryCap(cfg.memory_cap)
        self.keyframes = KeyframeStore(cfg.resolution_scale, cfg.keyframe_storage, cfg.keyframe_dir, cfg.view_cache_mb)
        self.schedule = TrainingSchedule(self.keyframes, sampler, cfg.coarse_steps, cfg.window, cfg.seed)
        self.steps = 0  # training steps taken (skipped and dropped ones excluded)
        self.skipped_steps = 0  # steps skipped for a non-finite loss or gradient
        self.stale_steps = 0  # steps dropped: rows were removed or overwritten during them
        # Seconds in optimize() and finish(): wall clock, and CPU time of the calling thread.
        self.train_time_s = 0.0
        self.train_cpu_s = 0.0
        self.last_loss: float | None = None
        self.timer = PhaseTimer()  # where the steps' time goes (metrics.json: mapping_step_ms)
        self.timer.sync = torch.cuda.synchronize if gaussian_map.device.type == "cuda" else None
        optimizer.reset()
        self.edit = MapEdit(gaussian_map, optimizer, strategy.state)
        # the strategy's own, sharing every per-row state with `edit`: its counts are the strategy's
        self.strategy_edit = MapEdit(gaussian_map, optimizer, strategy.state)
        self.gaussians_added = 0  # keyframes' Gaussians that entered the map

    # -- keyframes -------------------------------------------------------------------------
    def admit(self, frame: Frame, pose: np.ndarray, new: GaussianRows) -> torch.Tensor | None:
        """Which of a keyframe's new Gaussians enter the map (`Admission`); `pose` is its
        camera-to-world pose. Call under the map's lock."""
        camera = self.keyframes.training_camera(frame.camera)
        gm = self.gaussian_map
        w2c = torch.as_tensor(invert_pose(np.asarray(pose, dtype=np.float64)), dtype=torch.float32, device=gm.device)
        # the map as it was before this keyframe: in real time its trackable rows entered first
        # (SLAM.add_keyframe), and they must not count as covering the rest
        own = (gm.keyframe_id == int(new.keyframe_id[0])) if len(new) and len(gm) else None
        if own is not None and bool(own.any()):
            params = {k: v.detach()[~own] for k, v in gm.parameters().items()}
            view = KeyframeView(camera, w2c, lambda: self.render(w2c, camera, params), input_camera=frame.camera,
                                centres=params["means"])
        else:
            view = KeyframeView(camera, w2c, lambda: self.render(w2c, camera), input_camera=frame.camera,
                                centres=gm.means.detach())
        return self.admission.admit(new, view)

    def add_keyframe(self, frame: Frame, pose: np.ndarray, kind: KeyframeKind, new_rows: slice) -> None:
        """Keep `frame` (seen from `pose`, camera-to-world) as a training view; its Gaussians are
        at `new_rows` of the map (protected from the memory cap while others can go)."""
        keyframe = self.keyframes.add(frame, pose, kind)
        self.schedule.add(keyframe.id)
        self.gaussians_added += max(0, new_rows.stop - new_rows.start)
        with self.gaussian_map.lock:
            self.memory_cap.enforce(self.edit, protect=new_rows)

    def move_keyframes(self, updates: np.ndarray) -> None:
        """A loop closure moved keyframes 0..K-1 by `updates` ((K,4,4) world-frame rigid
        motions): their Gaussians (each row by its keyframe's motion, the optimiser's state
        with it: `MapEdit.move`) and their training views' poses. A step in flight is dropped
        (`stale_steps`)."""
        with self.gaussian_map.lock:
            self.edit.move(self.gaussian_map.keyframe_motion(updates))
            self.keyframes.move(updates)

    # -- training --------------------------------------------------------------------------
    def optimize(self, iterations: int) -> int:
        """Up to `iterations` steps; returns the steps attempted (skipped and dropped ones
        included); 0 while there is no keyframe or no Gaussian, so a real-time mapping loop
        waits instead of spinning."""
        start, cpu_start, done = time.perf_counter(), time.thread_time(), 0
        while done < iterations and len(self.keyframes) and len(self.gaussian_map):
            with self.timer("view"):
                view = self.schedule.next_view(self.gaussian_map.device)
            self.step(view)
            self.timer.steps += 1
            done += 1
        self._count_time(start, cpu_start)
        return done

    def step(self, view: TrainingView) -> bool:
        """One optimisation step on `view`; False when it was skipped (empty map, a non-finite
        loss or gradient) or dropped (rows removed during it)."""
        gm, timer = self.gaussian_map, self.timer
        with self._locked():
            params, rows, structure = gm.parameters(), len(gm), gm.structure_version
            if not self.keyframes.is_current(view):  # a loop closure moved its keyframe since it was taken
                self.stale_steps += 1
                return False
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
                grads = {k: _pad_rows(g, len(gm)) for k, g in grads.items()}  # rows appended meanwhile had no part
                self.edit.sync()
                with gm.updating() as live, torch.no_grad():
                    self.optimizer.step(live, grads)
                    live["colors"].clamp_(0.0, 1.0)
            self.steps += 1
            self.last_loss = float(loss.detach())
            with timer("strategy"):
                self.strategy.step_post_backward(self.strategy_edit,
                                                 StepInfo(self.steps, view, render, grads, self.last_loss))
                self.memory_cap.enforce(self.edit)  # a strategy that grew the map
        return True

    def finish(self) -> None:
        """After the last step: the strategy's wrap-up (e.g. a last pruning)."""
        start, cpu_start = time.perf_counter(), time.thread_time()
        with self.gaussian_map.lock:
            self.edit.sync()
            self.strategy.finish(self.strategy_edit)
        self._count_time(start, cpu_start)
        if self.memory_cap.prunings:
            log.info("memory cap (max_gaussians %s): %d Gaussians pruned in %d prunings",
                     self.cfg.memory_cap.max_gaussians, self.memory_cap.pruned, self.memory_cap.prunings)

    def render(self, world_to_camera: torch.Tensor, camera: Camera,
               params: dict[str, torch.Tensor] | None = None) -> RenderOutput:
        """Render the map (or `params`, the map's parameters taken earlier) differentiably;
        world_to_camera (4,4) float32 on the map's device."""
        p = params if params is not None else self.gaussian_map.parameters()
        return self.rasterizer.render(p["means"], p["quats"], torch.exp(p["log_scales"]),
                                      torch.sigmoid(p["opacity_logits"]), p["colors"], world_to_camera, camera)

    def render_view(self, pose: np.ndarray, camera: Camera) -> RenderOutput:
        """The map from `pose` (camera-to-world) with the trainer's rasteriser, no gradients."""
        return render_map(self.rasterizer, self.gaussian_map, pose, camera)

    # -- what it reports and keeps ---------------------------------------------------------
    def metrics(self) -> dict[str, Any]:
        """Counters and timings for metrics.json: among them the Gaussians keyframes added
        (gaussians_added) and those the strategy removed (gaussians_pruned), added by cloning
        and splitting (gaussians_densified) and gave new values (gaussians_relocated)."""
        first = self.keyframes[self.keyframes.ids[0]].camera if len(self.keyframes) else None
        edits = self.strategy_edit.counts
        return {**self.strategy.metrics(), **self.admission.metrics(), **self.memory_cap.metrics(),
                "gaussians_added": self.gaussians_added, "gaussians_pruned": edits["removed"],
                "gaussians_densified": edits["cloned"] + edits["split"], "gaussians_relocated": edits["updated"],
                "mapping_steps": self.steps, "mapping_skipped_steps": self.skipped_steps,
                "mapping_stale_steps": self.stale_steps, "mapping_step_ms": self.timer.per_step_ms(),
                "mapping_train_time_s": self.train_time_s, "mapping_train_cpu_s": self.train_cpu_s,
                "keyframe_memory_mb": self.keyframes.memory_bytes() / 2**20,
                "train_resolution": [first.width, first.height] if first else None}

    def state_dict(self) -> dict[str, Any]:
        """Keyframes, the training schedule (`TrainingSchedule.state_dict`),
        counters, the optimiser's and the strategy's state."""
        with self.gaussian_map.lock:  # copies (C calls) of what a mapping thread changes outside the lock
            return {"keyframes": self.keyframes.state_dict(), **self.schedule.state_dict(),
                    "steps": self.steps, "skipped_steps": self.skipped_steps, "stale_steps": self.stale_steps,
                    "train_time_s": self.train_time_s, "train_cpu_s": self.train_cpu_s, "last_loss": self.last_loss,
                    "optimizer": self.optimizer.state_dict(), "strategy": self.strategy.state_dict(),
                    "admission": self.admission.metrics(), "memory_cap": self.memory_cap.metrics(),
                    "gaussians_added": self.gaussians_added, "strategy_edits": dict(self.strategy_edit.counts)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back a `state_dict()`, after the map's rows are restored."""
        configured = self.keyframes.resolution_scale
        self.keyframes.load_state_dict(state["keyframes"])
        if self.keyframes.resolution_scale != configured:
            log.warning("resumed keyframes train at %g of the frame size, so new ones do too (not %g)",
                        self.keyframes.resolution_scale, configured)
        self.schedule.load_state_dict(state)
        self.steps, self.skipped_steps, self.stale_steps = (int(state[k]) for k in ("steps", "skipped_steps",
                                                                                     "stale_steps"))
        self.train_time_s, self.train_cpu_s = float(state["train_time_s"]), float(state["train_cpu_s"])
        self.last_loss = state["last_loss"]
        device = self.gaussian_map.device
        self.optimizer.load_state_dict(state["optimizer"])
        self.optimizer.edit_rows(lambda name, v: v.to(device))
        self.strategy.load_state_dict(state["strategy"])
        # checkpoints before admission and the cap were the trainer's kept their counters in the strategy's stats
        older = state["strategy"].get("stats", {})
        self.admission.skipped = int(state.get("admission", older).get("skipped_as_covered", 0))
        cap = state.get("memory_cap", older)
        # a checkpoint before 0.4 names the cap's counters as the memory guard's
        self.memory_cap.pruned = int(cap.get("pruned_by_memory_cap", cap.get("pruned_by_memory_guard", 0)))
        self.memory_cap.prunings = int(cap.get("memory_cap_prunings", cap.get("memory_guard_prunings", 0)))
        self.gaussians_added = int(state.get("gaussians_added", 0))  # 0 from a checkpoint older than the counters
        self.strategy_edit.counts.update({k: int(v) for k, v in state.get("strategy_edits", {}).items()})

    # -- internals -------------------------------------------------------------------------
    def _count_time(self, start: float, cpu_start: float) -> None:
        self.train_time_s += time.perf_counter() - start
        self.train_cpu_s += time.thread_time() - cpu_start

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
