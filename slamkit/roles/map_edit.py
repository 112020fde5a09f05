"""The shared operations that change which Gaussians the map holds (gsplat's strategy ops).

A densification strategy (`slamkit.roles.strategy.Strategy`) edits the map only through a
`MapEdit`: append, remove, duplicate, split, reset opacity, update rows, move rows (a loop
closure's correction). Each operation keeps
every per-row state aligned with the map's rows, in one place: the optimiser's (`MapOptimizer.
edit_rows`; rows that are new or whose values were replaced start with zero moments) and the
strategy's own statistics (`state`: copied for duplicates and split children, zero for new rows).
Call them under the map's lock (the trainer calls the strategy's hooks holding it). Each
`MapEdit` counts the Gaussians its operations added, removed and replaced (`counts`), so that a
run can say what its strategy did.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import torch

from slamkit.geometry.transforms import quat_to_rotmat
from slamkit.map.gaussian_map import GaussianMap, GaussianRows, RowMotion

if TYPE_CHECKING:
    from slamkit.roles.optimizer import MapOptimizer

log = logging.getLogger(__name__)


def _zeros_like_rows(v: torch.Tensor, n: int) -> torch.Tensor:
    return torch.zeros((n,) + tuple(v.shape[1:]), dtype=v.dtype, device=v.device)


class MapEdit:
    """Row operations on `gaussian_map` that keep `optimizer`'s per-row state and `state` (the
    strategy's per-row statistics: name -> tensor whose first dimension is the map's rows,
    edited in place) aligned with the map."""

    def __init__(self, gaussian_map: GaussianMap, optimizer: MapOptimizer, state: dict[str, torch.Tensor]):
        self.map = gaussian_map
        self.optimizer = optimizer
        self.state = state
        #: Gaussians appended, duplicated (cloned), added by splits (children less parents),
        #: removed, and given new values (update), through this object
        self.counts = {"appended": 0, "cloned": 0, "split": 0, "removed": 0, "updated": 0}

    def __len__(self) -> int:
        return len(self.map)

    @property
    def params(self) -> dict[str, torch.Tensor]:
        """The map's parameters, detached (read them; change them only through the operations)."""
        return {name: t.detach() for name, t in self.map.parameters().items()}

    # -- keeping the state sized to the map ------------------------------------------------------
    def sync(self) -> None:
        """Give rows appended at the end since the last operation (a keyframe's Gaussians) zero
        state. If the map lost rows other than through this object, the state can no longer be
        matched to rows: it is reset, with a warning."""
        n = len(self.map)
        rows = self.optimizer.num_rows()
        if rows > n or any(v.shape[0] > n for v in self.state.values()):
            log.warning("the Gaussian map lost rows outside the mapper; optimiser and strategy state reset")
            self.optimizer.reset()
            for k, v in self.state.items():
                self.state[k] = _zeros_like_rows(v, 0)
            rows = 0
        device = self.map.device
        if rows < n:
            def padded(name, v):
                v = v.to(device)
                return torch.cat([v, _zeros_like_rows(v, n - v.shape[0])])

            self.optimizer.edit_rows(padded)
        for k, v in self.state.items():
            if v.shape[0] < n or v.device != device:
                v = v.to(device)
                self.state[k] = torch.cat([v, _zeros_like_rows(v, n - v.shape[0])])

    # -- the operations ----------------------------------------------------------------------
    def append(self, rows: GaussianRows) -> slice:
        """Add `rows` at the end (zero optimiser and strategy state); returns their rows."""
        self.sync()
        added = self.map.append(rows)
        self.sync()
        self.counts["appended"] += added.stop - added.start
        return added

    def remove(self, drop: torch.Tensor) -> int:
        """Remove the rows where `drop` (bool, one per row) is true; returns how many."""
        removed = self._remove(drop)
        self.counts["removed"] += removed
        return removed

    def _remove(self, drop: torch.Tensor) -> int:
        self.sync()
        drop = torch.as_tensor(drop, dtype=torch.bool, device=self.map.device)
        removed = int(drop.sum())
        if removed:
            keep = ~drop
            self.map.keep(keep)
            self.optimizer.edit_rows(lambda name, v: v[keep.to(v.device)])
            for k, v in self.state.items():
                self.state[k] = v[keep.to(v.device)]
        return removed

    def duplicate(self, index: torch.Tensor) -> slice:
        """Append a copy of the rows at `index` (integer indices, repeats allowed): zero
        optimiser state, the strategy state of their originals. Returns the new rows."""
        added = self._duplicate(index)
        self.counts["cloned"] += added.stop - added.start
        return added

    def _duplicate(self, index: torch.Tensor) -> slice:
        self.sync()
        index = torch.as_tensor(index, dtype=torch.long, device=self.map.device)
        copied = {k: v[index.to(v.device)] for k, v in self.state.items()}
        added = self.map.append(self.map.rows(index))
        self.optimizer.edit_rows(lambda name, v: torch.cat([v, _zeros_like_rows(v, len(index))]))
        for k, v in copied.items():
            self.state[k] = torch.cat([self.state[k], v])
        return added

    def split(self, mask: torch.Tensor, children: int = 2, scale_divisor: float = 1.6,
              generator: torch.Generator | None = None) -> int:
        """Replace each Gaussian where `mask` is true by `children` Gaussians whose means are
        drawn from it (mean + R diag(s) n, n ~ N(0, I)) and whose scales are s / scale_divisor
        (3DGS's split). Returns the number of Gaussians split."""
        self.sync()
        index = torch.nonzero(torch.as_tensor(mask, device=self.map.device)).squeeze(1)
        if len(index) == 0:
            return 0
        parents = self.map.rows(index)
        R = quat_to_rotmat(parents.quats)
        s = torch.exp(parents.log_scales)
        start = len(self.map)
        for _ in range(children):
            noise = torch.randn(s.shape, generator=generator, device=s.device, dtype=s.dtype)
            child = self.map.rows(index)
            child.means = parents.means + torch.einsum("nij,nj->ni", R, s * noise)
            child.log_scales = parents.log_scales - math.log(scale_divisor)
            self._duplicate(index)
            self._overwrite(slice(len(self.map) - len(index), len(self.map)), child.entering_now())
        drop = torch.zeros(len(self.map), dtype=torch.bool, device=self.map.device)
        drop[index] = True
        self._remove(drop)
        assert len(self.map) == start + (children - 1) * len(index)
        self.counts["split"] += (children - 1) * len(index)
        return len(index)

    def reset_opacity(self, max_opacity: float) -> None:
        """Clamp every opacity to at most `max_opacity` and forget the opacity moments (3DGS's
        opacity reset)."""
        self.sync()
        self.map.clamp_opacity(max_opacity)
        self.optimizer.edit_rows(lambda name, v: torch.zeros_like(v) if name == "opacity_logits" else v)

    def update(self, index: torch.Tensor, rows: GaussianRows) -> None:
        """Give the rows at `index` (integer indices) the parameters and flags of `rows` and
        zero optimiser state (e.g. relocating dead Gaussians, as 3DGS-MCMC does)."""
        self.sync()
        index = torch.as_tensor(index, dtype=torch.long, device=self.map.device)
        self._overwrite(index, rows)
        self.counts["updated"] += len(index)

    def move(self, motion: RowMotion) -> None:
        """Move every row rigidly by `motion` (`GaussianMap.move_rows`: means, rotations and
        their entry geometry); the optimiser's state follows (`MapOptimizer.move_rows`), the
        strategy's statistics (gradient norms, counts: unchanged by a rigid motion) stay."""
        self.sync()
        self.map.move_rows(motion)
        self.optimizer.move_rows(motion)

    def _overwrite(self, index, rows: GaussianRows) -> None:
        self.map.overwrite(index, rows)

        def zero(name, v):
            v = v.clone()
            v[index] = 0
            return v

        self.optimizer.edit_rows(zero)
