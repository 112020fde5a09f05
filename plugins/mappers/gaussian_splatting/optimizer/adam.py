"""`mapper/optimizer=adam`: torch.optim.Adam over the map's parameters, one learning rate each.

The learning rates are the reference code's (GS-ICP SLAM, as 3DGS): means 4e-6 (constant),
colours 0.0025, opacity logits 0.05, log scales 0.005, quaternions 0.001; eps 1e-15. The map's
rows change between steps (keyframes append, strategies remove, duplicate, split): the shared
row operations edit Adam's moments through `edit_rows` (new rows start at zero, as gsplat's
strategy ops do), and a parameter tensor the map replaced takes over its predecessor's state at
the next step. Adam's step count is one per parameter tensor (torch's), so a row that joins late
is bias-corrected as if it had been there from the start: its first updates are up to ~3x
larger than a fresh Adam's (`mapper/optimizer=visible_adam` counts steps per row).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from slamkit.map.gaussian_map import PARAMETERS
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import MapOptimizer, PluginConfig, RunContext, require
from slamkit.roles.optimizer import rotated_moments

#: Which config field holds each parameter's learning rate.
LR_FIELDS = {"means": "lr_means", "quats": "lr_quats", "log_scales": "lr_scales", "opacity_logits": "lr_opacity",
             "colors": "lr_colors"}


@dataclass
class AdamConfig(PluginConfig):
    """Adam's settings (the learning rates: the reference code's)."""

    #: learning rate of the means (metres)
    lr_means: float = 4e-6
    #: learning rate of the colours
    lr_colors: float = 0.0025
    #: learning rate of the opacities (logit space)
    lr_opacity: float = 0.05
    #: learning rate of the scales (log space)
    lr_scales: float = 0.005
    #: learning rate of the rotations (quaternions)
    lr_quats: float = 0.001
    #: Adam's epsilon (1e-15 as 3DGS)
    eps: float = 1e-15
    #: Adam's first-moment decay rate
    beta1: float = 0.9
    #: Adam's second-moment decay rate
    beta2: float = 0.999
    #: torch's fused Adam kernel: the same update to float precision, one call per parameter instead of ~8
    fused: bool = True

    def validate(self) -> None:
        for field in LR_FIELDS.values():
            v = getattr(self, field)
            require(v >= 0 and v == v and v != float("inf"), f"mapper.optimizer.{field}", "a learning rate >= 0", v)
        require(self.eps > 0, "mapper.optimizer.eps", "> 0", self.eps)
        require(0 <= self.beta1 < 1, "mapper.optimizer.beta1", "in [0, 1)", self.beta1)
        require(0 <= self.beta2 < 1, "mapper.optimizer.beta2", "in [0, 1)", self.beta2)

    def learning_rates(self) -> dict[str, float]:
        return {name: float(getattr(self, field)) for name, field in LR_FIELDS.items()}


class TorchAdam(MapOptimizer):
    """torch.optim.Adam with one parameter group per map parameter (see the module docstring)."""

    def __init__(self, cfg: AdamConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        # torch's first Adam imports torch._dynamo (seconds, holding the GIL): at start-up here,
        # not in the first mapping step (in real time that is during the stream, and it stalled
        # the tracking thread as well)
        torch.optim.Adam([torch.zeros(1, requires_grad=True)], fused=cfg.fused)
        self.adam: torch.optim.Adam | None = None
        self.restored: dict[str, dict] = {}  # state from a checkpoint, until Adam is made

    def _groups(self) -> dict[str, dict]:
        return {g["name"]: g for g in self.adam.param_groups} if self.adam is not None else {}

    def step(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> None:
        if self.adam is None:
            lrs = self.cfg.learning_rates()
            self.adam = torch.optim.Adam([{"params": [params[n]], "lr": lrs[n], "name": n} for n in PARAMETERS],
                                         betas=(self.cfg.beta1, self.cfg.beta2), eps=self.cfg.eps,
                                         fused=self.cfg.fused)
            for name, state in self.restored.items():
                self.adam.state[params[name]] = state
            self.restored = {}
        for name, group in self._groups().items():
            old, new = group["params"][0], params[name]
            if old is not new:  # the map replaced the tensor; its state rows were kept aligned
                state = self.adam.state.pop(old, None)
                group["params"] = [new]
                if state is not None:
                    self.adam.state[new] = state
            grad = grads.get(name)
            # the fused kernel reads grad as laid out like its parameter (an expanded, stride-0
            # gradient, as an autograd sum's, gave NaN moments)
            new.grad = grad.contiguous() if grad is not None else None
        self.adam.step()
        for p in params.values():
            p.grad = None

    def _state(self, name: str) -> dict:
        if self.adam is None:
            return self.restored.get(name, {})
        group = self._groups().get(name)
        return self.adam.state.get(group["params"][0], {}) if group is not None else {}

    def num_rows(self) -> int:
        state = self._state("means")
        return int(state["exp_avg"].shape[0]) if "exp_avg" in state else 0

    def edit_rows(self, edit) -> None:
        for name in PARAMETERS:
            state = self._state(name)
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key] = edit(name, state[key])

    def move_rows(self, motion) -> None:
        """Adam's moments follow rows a loop closure moved (`rotated_moments`)."""
        for name, linear in (("means", motion.rotations), ("quats", motion.quat_maps)):
            state = self._state(name)
            if "exp_avg" in state:
                state["exp_avg"], state["exp_avg_sq"] = rotated_moments(linear, state["exp_avg"], state["exp_avg_sq"])

    def reset(self) -> None:
        self.adam = None
        self.restored = {}

    def state_dict(self) -> dict:
        """Adam's moments and step count of each parameter (those it has state for)."""
        return {name: dict(self._state(name)) for name in PARAMETERS if self._state(name)}

    def load_state_dict(self, state: dict) -> None:
        """Adam's state from `state_dict()`; it becomes the state of the map's parameters at the
        next step."""
        self.adam = None
        self.restored = {name: {k: torch.as_tensor(v) for k, v in s.items()} for name, s in state.items()}


@hookimpl
def slamkit_plugins():
    return [PluginSpec("adam", TorchAdam, AdamConfig)]
