"""slamkit-mcmc: relocation of dead Gaussians as in 3DGS-MCMC, as a third-party densification
strategy for slamkit's `gaussian_splatting` mapper (``mapper/strategy=mcmc``).

How the plugin is wired (the whole of it; see docs/plugin_guide.md, section 9)
-----------------------------------------------------------------------------
1. `MCMCStrategy` subclasses the part `slamkit.roles.Strategy` and overrides the hooks
   `step_post_backward` (relocate / grow every `refine_every` steps) and `finish`. It changes
   the map only through the `MapEdit` the mapper hands it (`remove`, `duplicate`, `update`),
   which keeps the optimiser's per-row moments aligned with the rows.
2. `MCMCConfig` derives from `slamkit.roles.StrategyConfig`; `resolve` fills `max_scale` from
   the dataset's tuning (`DatasetTuning.max_gaussian_scale`). What every strategy gets from the
   trainer (which Gaussians enter, `mapper.admission.*`; the memory cap,
   `mapper.memory_cap.max_gaussians`) needs nothing here.
3. The hook `slamkit_plugins` returns ``PluginSpec("mcmc", MCMCStrategy, MCMCConfig)``.
4. pyproject.toml names this module in the entry-point group ``slamkit``.

The method (Kheradmand et al., "3D Gaussian Splatting as Markov Chain Monte Carlo", 2024)
------------------------------------------------------------------------------------------
Every `refine_every` training steps:

1. prune, as GS-ICP SLAM does, the Gaussians larger than the scene allows (largest standard
   deviation > `max_scale` metres) or with a non-finite parameter;
2. relocate the dead Gaussians (opacity < `min_opacity`): each is moved onto a live Gaussian
   drawn with probability proportional to opacity. A source drawn k times and its k copies
   share its opacity o and footprint: each gets opacity o' = 1 - (1 - o)^(1/(k+1)), so that
   the k+1 stacked Gaussians are as opaque at the centre as the source was, and its standard
   deviations times o / D with

       D = sum_{i=1..k+1} sum_{j=0..i-1} C(i-1, j) (-1)^j o'^(j+1) / sqrt(j+1)
         = 2/sqrt(pi) * integral_0^inf 1 - (1 - o' e^(-t^2))^(k+1) dt,

   3DGS-MCMC's rule for an unchanged integrated opacity (the integral form, which follows from
   1/sqrt(j+1) = 2/sqrt(pi) integral e^(-(j+1) t^2) dt and two binomial sums, is free of the
   alternating sum's cancellation for large k). The map keeps its size;
3. grow: draw `grow_fraction` x (map size) more sources the same way, up to `cap_max`
   Gaussians in the map, and append their copies by the same rule;
4. the trainer then applies the memory cap (`mapper.memory_cap.max_gaussians`), as after every
   strategy.

After the last training step (`finish`), dead Gaussians are pruned rather than relocated (a copy
made then would never be trained), together with the oversized and non-finite ones.

Adapted to SLAM:

- 3DGS-MCMC perturbs every mean with opacity-weighted noise at each step (its Langevin term),
  which separates a source from its copies. `MapEdit` can change a parameter only by zeroing
  the row's optimiser moments, so per-step noise would reset Adam for every nearly transparent
  Gaussian at every step. Instead each copy is placed once, when it is made, at a point drawn
  from its source's (shrunk) Gaussian, as 3DGS's split places its children (`jitter`).
- A relocated or added copy is not trackable: it duplicates its source's position, and two
  targets on one point would count it twice in G-ICP (the reason map growth never makes a
  Gaussian trackable next to a trackable one); its covariance is also no longer a k-NN surface
  estimate. Its `keyframe_id` is its source's. The source keeps its flag (with a smaller
  opacity and footprint, which the tracker sees at its next tracking keyframe).
- No warm-up (`refine_start_iter`): a SLAM run trains a few hundred to a few thousand steps,
  and keyframes keep adding Gaussians, so refinement starts with the first period.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields

import torch

from slamkit.geometry.transforms import quat_to_rotmat
from slamkit.map.gaussian_map import GaussianRows
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import MapEdit, RunContext, StepInfo, Strategy, StrategyConfig, require

log = logging.getLogger(__name__)

#: Opacities are kept below 1 - this so that their logit stays finite.
OPACITY_CEILING_GAP = 1e-6
#: Quadrature of the footprint integral: t in [0, INTEGRAL_END] (the integrand is below
#: (k+1) e^(-36) beyond), INTEGRAL_POINTS trapezoid nodes (a smooth, fast-decaying integrand:
#: the error is far below float32 precision; tests/test_mcmc.py checks it against the sum).
INTEGRAL_END = 6.0
INTEGRAL_POINTS = 97


@dataclass
class MCMCConfig(StrategyConfig):
    """Options of ``mapper/strategy=mcmc``: relocation of dead Gaussians and growth by sampling."""

    #: training steps between relocations (and growth)
    refine_every: int = 100
    #: a less opaque Gaussian is dead: relocated onto a live one (pruned after the last step)
    min_opacity: float = 0.005
    #: each refinement adds this fraction of the map's size, sampled like relocations (0: relocation only)
    grow_fraction: float = 0.05
    #: no growth beyond this many Gaussians (keyframes still add theirs; mapper.memory_cap bounds the map)
    cap_max: int = 300_000
    #: place each copy at a point drawn from its source's Gaussian instead of on its mean
    jitter: bool = True
    #: metres; prune Gaussians whose largest standard deviation exceeds it (null: the dataset's max_gaussian_scale)
    max_scale: float | None = None
    #: seed of the sampling's random generator
    seed: int = 0

    def validate(self) -> None:
        super().validate()
        require(self.refine_every >= 1, "mapper.strategy.refine_every", "an integer >= 1", self.refine_every)
        require(0 < self.min_opacity < 1, "mapper.strategy.min_opacity", "in (0, 1)", self.min_opacity)
        require(0 <= self.grow_fraction <= 1, "mapper.strategy.grow_fraction", "in [0, 1]", self.grow_fraction)
        require(self.cap_max >= 1, "mapper.strategy.cap_max", "an integer >= 1", self.cap_max)
        require(self.max_scale is None or self.max_scale > 0, "mapper.strategy.max_scale", "null or > 0 metres",
                self.max_scale)
        require(0 <= self.seed < 2**63, "mapper.strategy.seed", "an integer from 0 to 2^63 - 1 (torch's seed range)",
                self.seed)

    def resolve(self, context: RunContext) -> MCMCConfig:
        return self.fill_nulls(max_scale=context.tuning.max_gaussian_scale)


def shared_opacity(opacity: torch.Tensor, copies: torch.Tensor) -> torch.Tensor:
    """The opacity each of a source and its `copies` copies takes so that the stack is as
    opaque as the source alone: 1 - (1 - o)^(1/(copies + 1))."""
    return 1.0 - (1.0 - opacity) ** (1.0 / (copies + 1.0))


def scale_factor(opacity: torch.Tensor, new_opacity: torch.Tensor, copies: torch.Tensor) -> torch.Tensor:
    """The factor on a source's standard deviations after it is split into copies + 1
    Gaussians of opacity `new_opacity`: o / D (the module docstring's D), computed in float64."""
    o, o_new = opacity.double(), new_opacity.double()
    t = torch.linspace(0.0, INTEGRAL_END, INTEGRAL_POINTS, dtype=torch.float64, device=o.device)
    profile = o_new[:, None] * torch.exp(-t * t)[None, :]
    integrand = 1.0 - (1.0 - profile) ** (copies.double()[:, None] + 1.0)
    D = 2.0 / math.sqrt(math.pi) * torch.trapezoid(integrand, t, dim=1)
    return (o / D).to(opacity.dtype)


def concat_rows(a: GaussianRows, b: GaussianRows) -> GaussianRows:
    """The rows of `a` followed by those of `b`."""
    return GaussianRows(**{f.name: torch.cat([getattr(a, f.name), getattr(b, f.name)]) for f in fields(GaussianRows)})


class MCMCStrategy(Strategy):
    """Relocation of dead Gaussians and opacity-proportional growth (see the module docstring).
    stats (metrics.json): mcmc_relocated, mcmc_added, mcmc_pruned (oversized, non-finite, and
    dead ones after the last step), mcmc_refinements."""

    def __init__(self, cfg: MCMCConfig, context: RunContext = RunContext()):
        super().__init__(cfg, context)
        require(cfg.max_scale is not None, "mapper.strategy.max_scale", "a value (MCMCConfig.resolve fills it)", None)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.stats.update(mcmc_relocated=0, mcmc_added=0, mcmc_pruned=0, mcmc_refinements=0)

    # -- the hooks ---------------------------------------------------------------------------
    def step_post_backward(self, edit: MapEdit, info: StepInfo) -> None:
        if info.step % self.cfg.refine_every == 0:
            self.refine(edit)

    def finish(self, edit: MapEdit) -> None:
        self.stats["mcmc_pruned"] += edit.remove(self.broken(edit) | self.dead(edit))

    # -- one refinement ----------------------------------------------------------------------
    def refine(self, edit: MapEdit) -> None:
        """Prune, relocate, grow (the module docstring's steps 1-3; the trainer then applies the cap)."""
        pruned = edit.remove(self.broken(edit))
        relocated = self.relocate(edit)
        added = self.grow(edit)
        self.stats["mcmc_pruned"] += pruned
        self.stats["mcmc_relocated"] += relocated
        self.stats["mcmc_added"] += added
        self.stats["mcmc_refinements"] += 1
        log.debug("mcmc: pruned %d, relocated %d, added %d; %d Gaussians", pruned, relocated, added, len(edit))

    def opacity(self, edit: MapEdit) -> torch.Tensor:
        return torch.sigmoid(edit.params["opacity_logits"])

    def dead(self, edit: MapEdit) -> torch.Tensor:
        """True for the Gaussians less opaque than min_opacity."""
        return self.opacity(edit) < self.cfg.min_opacity

    def broken(self, edit: MapEdit) -> torch.Tensor:
        """True for the Gaussians larger than max_scale or with a non-finite parameter."""
        p = edit.params
        drop = torch.exp(p["log_scales"]).max(dim=1).values > self.cfg.max_scale
        for t in p.values():
            drop |= ~torch.isfinite(t).reshape(len(t), -1).all(dim=1)
        return drop

    def relocate(self, edit: MapEdit) -> int:
        """Move every dead Gaussian onto a live one; returns how many moved."""
        dead = self.dead(edit)
        n_dead = int(dead.sum())
        if n_dead == 0 or n_dead == len(edit):
            return 0
        sources = self.draw(self.opacity(edit) * ~dead, n_dead)
        self.copy_onto(edit, sources, torch.nonzero(dead).squeeze(1))
        return n_dead

    def grow(self, edit: MapEdit) -> int:
        """Append copies of sampled live Gaussians, grow_fraction of the map's size, up to
        cap_max; returns how many were added."""
        n = len(edit)
        n_add = min(self.cfg.cap_max, int(n * (1.0 + self.cfg.grow_fraction))) - n
        live = ~self.dead(edit)
        if n_add <= 0 or not bool(live.any()):
            return 0
        sources = self.draw(self.opacity(edit) * live, n_add)
        added = edit.duplicate(sources)
        self.copy_onto(edit, sources, torch.arange(added.start, added.stop, device=sources.device))
        return n_add

    # -- the MCMC move -----------------------------------------------------------------------
    def draw(self, weights: torch.Tensor, n: int) -> torch.Tensor:
        """n row indices drawn with replacement with probability proportional to `weights`
        (on the CPU with the strategy's generator, so that runs repeat on any device)."""
        drawn = torch.multinomial(weights.detach().double().cpu(), n, replacement=True, generator=self.generator)
        return drawn.to(weights.device)

    def copy_onto(self, edit: MapEdit, sources: torch.Tensor, targets: torch.Tensor) -> None:
        """Make row targets[i] a copy of row sources[i]; every source and its copies take the
        shared opacity and shrunk scales; one `update`, which zeroes their optimiser moments."""
        copies = torch.bincount(sources, minlength=len(edit))
        unique = torch.nonzero(copies).squeeze(1)
        shared = self.shrunk(edit.map.rows(unique), copies[unique])
        clones = shared.select(torch.searchsorted(unique, sources))
        clones.trackable = torch.zeros_like(clones.trackable)
        if self.cfg.jitter:
            clones.means = clones.means + self.offsets(clones)
        edit.update(torch.cat([unique, targets]), concat_rows(shared, clones))

    def shrunk(self, rows: GaussianRows, copies: torch.Tensor) -> GaussianRows:
        """`rows` with the opacity and scales each of them and its `copies` copies share."""
        o = torch.sigmoid(rows.opacity_logits)
        o_new = shared_opacity(o, copies.to(o.dtype)).clamp(self.cfg.min_opacity, 1.0 - OPACITY_CEILING_GAP)
        factor = scale_factor(o, o_new, copies)
        rows.opacity_logits = torch.logit(o_new)
        rows.log_scales = rows.log_scales + torch.log(factor)[:, None]
        return rows

    def offsets(self, rows: GaussianRows) -> torch.Tensor:
        """(N,3) metres: one draw from each row's Gaussian, R diag(s) n with n ~ N(0, I)."""
        noise = torch.randn(rows.means.shape, generator=self.generator, dtype=rows.means.dtype)
        R = quat_to_rotmat(rows.quats)
        return torch.einsum("nij,nj->ni", R, torch.exp(rows.log_scales) * noise.to(rows.means.device))


@hookimpl
def slamkit_plugins():
    return [PluginSpec("mcmc", MCMCStrategy, MCMCConfig)]
