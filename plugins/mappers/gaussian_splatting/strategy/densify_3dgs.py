"""`mapper/strategy=3dgs`: 3D Gaussian Splatting's adaptive density control (Kerbl et al. 2023), the
paper's Table 8b ablation (GS-ICP SLAM itself does not densify: `mapper/strategy=gsicp`).

Every training step accumulates, for each Gaussian the step saw, the norm of the loss's
gradient with respect to its projected mean in 3DGS's NDC units, approximated from the 3D
gradient: |dL/d(x, y)_camera| z W / (2 fx). Every `densify_every` steps the Gaussians whose
average reaches `grad_threshold` are cloned (largest scale <= `split_above_scale` metres) or
split in two (scales / 1.6), within the `densify_max_gaussians` budget; then the map is pruned
(as `gsicp`; also every `prune_every` steps, and never when prune_every = 0). Every
`reset_opacity_every` steps opacities are
clamped to 0.01.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import MapEdit, RunContext, StepInfo, require
from slamkit_plugins.mappers.gaussian_splatting.strategy.gsicp import PruneConfig, PruneStrategy

#: A split Gaussian's children have its scales divided by this (3DGS).
SPLIT_SCALE_DIVISOR = 1.6
#: Opacity after a reset (3DGS).
RESET_OPACITY = 0.01


@dataclass
class Densify3DGSConfig(PruneConfig):
    """3DGS's adaptive density control on top of the pruning schedule."""

    #: training steps between densifications
    densify_every: int = 100
    #: the average view-space positional gradient (NDC units) from which a Gaussian is densified
    grad_threshold: float = 0.0002
    #: metres; a selected Gaussian whose largest scale is above this is split, else cloned
    split_above_scale: float = 0.05
    #: no densification beyond this many Gaussians
    densify_max_gaussians: int = 2_000_000
    #: training steps between opacity resets (0: never)
    reset_opacity_every: int = 3000
    #: the seed of the split's random offsets
    seed: int = 0

    def validate(self) -> None:
        super().validate()
        require(self.densify_every >= 1, "mapper.strategy.densify_every", "an integer >= 1", self.densify_every)
        require(self.grad_threshold > 0, "mapper.strategy.grad_threshold", "> 0", self.grad_threshold)
        require(self.split_above_scale > 0, "mapper.strategy.split_above_scale", "> 0 metres", self.split_above_scale)
        require(self.densify_max_gaussians >= 0, "mapper.strategy.densify_max_gaussians", ">= 0",
                self.densify_max_gaussians)
        require(self.reset_opacity_every >= 0, "mapper.strategy.reset_opacity_every", "an integer >= 0 (0 = never)",
                self.reset_opacity_every)
        require(0 <= self.seed < 2**64, "mapper.strategy.seed", "an integer from 0 to 2^64 - 1 (torch's seed range)",
                self.seed)


class Densify3DGSStrategy(PruneStrategy):
    """Clone / split / prune / opacity reset (see the module docstring)."""

    def __init__(self, cfg: Densify3DGSConfig, context: RunContext = RunContext()):
        super().__init__(cfg, context)
        self.state = {"grad_sum": torch.zeros(0), "grad_count": torch.zeros(0)}
        self.generator = torch.Generator().manual_seed(cfg.seed)

    def state_dict(self) -> dict:
        return {**super().state_dict(), "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        if "generator" in state:
            self.generator.set_state(torch.as_tensor(state["generator"], dtype=torch.uint8))

    def step_post_backward(self, edit: MapEdit, info: StepInfo) -> None:
        cfg = self.cfg
        if "means" in info.grads:
            self.accumulate(edit, info)
        densify_now = info.step % cfg.densify_every == 0
        if densify_now:
            self.densify(edit)
        # prune_every = 0 turns pruning off, at densifications too (Table 8b's "densify, no pruning").
        if cfg.prune_every and (densify_now or info.step % cfg.prune_every == 0):
            self.prune(edit)
        if cfg.reset_opacity_every and info.step % cfg.reset_opacity_every == 0:
            edit.reset_opacity(RESET_OPACITY)

    def accumulate(self, edit: MapEdit, info: StepInfo) -> None:
        """Add this step's view-space gradient norms to the Gaussians it saw (non-zero gradient,
        in front of the camera); rows appended since the step began have no gradient."""
        g3, W, cam = info.grads["means"], info.view.world_to_camera, info.view.camera
        n = len(g3)
        z = edit.params["means"][:n] @ W[2, :3] + W[2, 3]
        g = (g3 @ W[:3, :3].T)[:, :2].norm(dim=1) * z.clamp_min(0) * cam.width / (2 * cam.fx)
        seen = (g3 != 0).any(dim=1) & (z > 0.01)
        self.state["grad_sum"][:n][seen] += g[seen]
        self.state["grad_count"][:n][seen] += 1

    def densify(self, edit: MapEdit) -> None:
        """Clone and split the Gaussians with a large average gradient, within the budget."""
        cfg, n = self.cfg, len(edit)
        avg = self.state["grad_sum"] / self.state["grad_count"].clamp_min(1)
        selected = avg >= cfg.grad_threshold
        room = cfg.densify_max_gaussians - n
        if room <= 0:
            selected[:] = False
        elif int(selected.sum()) > room // 2:  # the largest gradients within the budget (a split adds a row)
            idx = torch.nonzero(selected).squeeze(1)
            selected = torch.zeros_like(selected)
            selected[idx[torch.argsort(avg[idx], descending=True)[: room // 2]]] = True
        large = torch.exp(edit.params["log_scales"]).max(dim=1).values > cfg.split_above_scale
        clone, split = selected & ~large, selected & large
        edit.duplicate(torch.nonzero(clone).squeeze(1))
        split = torch.cat([split, torch.zeros(len(edit) - n, dtype=torch.bool)])
        edit.split(split, 2, SPLIT_SCALE_DIVISOR, self.generator)
        for v in self.state.values():
            v.zero_()


@hookimpl
def slamkit_plugins():
    return [PluginSpec("3dgs", Densify3DGSStrategy, Densify3DGSConfig)]
