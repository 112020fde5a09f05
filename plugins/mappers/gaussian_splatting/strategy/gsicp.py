"""`mapper/strategy=gsicp`: GS-ICP SLAM's map upkeep (paper Sec. 3.2, Table 8b): no densification
(keyframes add the Gaussians), only pruning: every `prune_every` training steps and after the
last one (`prune_at_finish`; the reference code stops without it), the Gaussians that are
nearly transparent, larger than the scene allows, or have a non-finite parameter are removed."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import MapEdit, RunContext, StepInfo, Strategy, StrategyConfig, method_setting, require


@dataclass
class PruneConfig(StrategyConfig):
    """GS-ICP SLAM's pruning schedule."""

    #: training steps between prunings (0: never)
    prune_every: int = method_setting(200)
    #: prune Gaussians less opaque than this
    prune_min_opacity: float = 0.005
    #: metres; prune Gaussians whose largest standard deviation exceeds it (null: the dataset's max_gaussian_scale)
    max_scale: float | None = None
    #: prune once more after the last training step (the reference code does not)
    prune_at_finish: bool = method_setting(True)

    def validate(self) -> None:
        super().validate()
        require(self.prune_every >= 0, "mapper.strategy.prune_every", "an integer >= 0 (0 = never)", self.prune_every)
        require(0 <= self.prune_min_opacity < 1, "mapper.strategy.prune_min_opacity", "in [0, 1)",
                self.prune_min_opacity)
        require(self.max_scale is None or self.max_scale > 0, "mapper.strategy.max_scale", "null or > 0 metres",
                self.max_scale)

    def resolve(self, context: RunContext) -> PruneConfig:
        return self.fill_nulls(max_scale=context.tuning.max_gaussian_scale)


class PruneStrategy(Strategy):
    """Pruning on a schedule (see the module docstring)."""

    def __init__(self, cfg: PruneConfig, context: RunContext = RunContext()):
        super().__init__(cfg, context)
        require(cfg.max_scale is not None, "mapper.strategy.max_scale", "a value (PruneConfig.resolve fills it)", None)

    def prune_mask(self, edit: MapEdit) -> torch.Tensor:
        """True for the Gaussians to remove: opacity < prune_min_opacity, largest scale >
        max_scale, or a parameter that is not finite."""
        p = edit.params
        drop = torch.sigmoid(p["opacity_logits"]) < self.cfg.prune_min_opacity
        drop |= torch.exp(p["log_scales"]).max(dim=1).values > self.cfg.max_scale
        for t in p.values():
            drop |= ~torch.isfinite(t).reshape(len(t), -1).all(dim=1)
        return drop

    def prune(self, edit: MapEdit) -> int:
        """Prune now; returns the number of Gaussians removed."""
        return edit.remove(self.prune_mask(edit))

    def step_post_backward(self, edit: MapEdit, info: StepInfo) -> None:
        if self.cfg.prune_every and info.step % self.cfg.prune_every == 0:
            self.prune(edit)

    def finish(self, edit: MapEdit) -> None:
        if self.cfg.prune_every and self.cfg.prune_at_finish:
            self.prune(edit)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("gsicp", PruneStrategy, PruneConfig)]
