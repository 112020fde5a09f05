"""`optimizer=visible_adam`: Adam with a step count per map row, updating only the rows a step
saw.

Each row is updated exactly as Adam would update it if the steps in which it had a gradient
were its only steps: its own step count t drives the bias correction, so a Gaussian added by a
late keyframe starts like a fresh Adam, and a row the step did not render (zero gradient for
every parameter) keeps its parameters and moments (the "sparse" or "visible" Adam of the 3DGS
literature; `only_visible=false` updates every row, moments decaying where the gradient is
zero). With every row visible at every step and the same age, it equals torch.optim.Adam
(tests/test_optimizers.py). The same learning rates as `optimizer=adam`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import MapOptimizer
from slamkit_plugins.optimizers.adam import AdamConfig

#: The per-row step count's key among the state tensors `edit_rows` sees.
STEPS = "steps"


@dataclass
class VisibleAdamConfig(AdamConfig):
    """only_visible: update only the rows with a non-zero gradient (rows the step rendered);
    false updates every row (moments decay where the gradient is zero)."""

    only_visible: bool = True


class VisibleAdam(MapOptimizer):
    """Per-row Adam (see the module docstring). State: first and second moments per parameter,
    one step count per row."""

    def __init__(self, cfg: VisibleAdamConfig):
        self.cfg = cfg
        self.lrs = cfg.learning_rates()
        self.moments: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        self.steps = torch.zeros(0)

    def num_rows(self) -> int:
        return int(self.steps.shape[0])

    def edit_rows(self, edit) -> None:
        self.moments = {name: (edit(name, m), edit(name, v)) for name, (m, v) in self.moments.items()}
        self.steps = edit(STEPS, self.steps)

    def reset(self) -> None:
        self.moments, self.steps = {}, torch.zeros(0)

    @torch.no_grad()
    def step(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> None:
        n = next(iter(params.values())).shape[0]
        if not self.moments:
            device = next(iter(params.values())).device
            self.moments = {k: (torch.zeros_like(p), torch.zeros_like(p)) for k, p in params.items()}
            self.steps = torch.zeros(n, device=device)
        rows = self._rows(grads, n)
        self.steps[rows] += 1
        b1, b2 = self.cfg.beta1, self.cfg.beta2
        t = self.steps[rows]
        c1, c2 = 1 - b1**t, 1 - b2**t
        for name, p in params.items():
            g = grads.get(name)
            if g is None:
                continue
            m, v = self.moments[name]
            g = g[rows]
            m_rows = m[rows].mul_(b1).add_(g, alpha=1 - b1)
            v_rows = v[rows].mul_(b2).addcmul_(g, g, value=1 - b2)
            shape = (-1,) + (1,) * (p.dim() - 1)
            update = (m_rows / c1.view(shape)) / (v_rows / c2.view(shape)).sqrt_().add_(self.cfg.eps)
            m[rows], v[rows] = m_rows, v_rows
            p[rows] -= self.lrs[name] * update

    def _rows(self, grads: dict[str, torch.Tensor], n: int) -> torch.Tensor:
        """The rows to update: those with a non-zero gradient (or every row)."""
        if not self.cfg.only_visible:
            return torch.arange(n, device=self.steps.device)
        seen = torch.zeros(n, dtype=torch.bool, device=self.steps.device)
        for g in grads.values():
            seen |= (g != 0).reshape(n, -1).any(dim=1)
        return torch.nonzero(seen).squeeze(1)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("visible_adam", VisibleAdam, VisibleAdamConfig)]
