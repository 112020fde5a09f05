"""The Gaussian map shared by tracking and mapping, and the rows that enter it."""

from __future__ import annotations

import threading
from dataclasses import dataclass, fields

import numpy as np
import torch

from slamkit.geometry.transforms import covariance_from_scales, scales_from_covariance

#: The optimisable parameters, in this order everywhere (GaussianMap, GaussianRows, optimisers).
PARAMETERS = ("means", "quats", "log_scales", "opacity_logits", "colors")
#: The geometry a Gaussian entered the map with, which no optimiser changes: entry field -> parameter.
ENTRY_GEOMETRY = {"entry_means": "means", "entry_quats": "quats", "entry_log_scales": "log_scales"}


def _logit(p: np.ndarray) -> np.ndarray:
    return np.log(p / (1 - p))


@dataclass
class GaussianRows:
    """Gaussians that are not (or not yet) rows of a map, in the map's parameterisation: torch
    tensors with one row each. means (N,3) world metres; quats (N,4) (w, x, y, z); log_scales
    (N,3) log of standard deviations in metres; opacity_logits (N,); colors (N,3) RGB in [0, 1];
    trackable (N,) bool; keyframe_id (N,) int64 (the keyframe that added it, -1 = none);
    entry_means, entry_quats, entry_log_scales: the geometry it entered the map with (what a
    tracker aligns to, see GaussianMap)."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    trackable: torch.Tensor
    keyframe_id: torch.Tensor
    entry_means: torch.Tensor
    entry_quats: torch.Tensor
    entry_log_scales: torch.Tensor

    @classmethod
    def from_parameters(cls, params: dict[str, torch.Tensor], trackable: torch.Tensor,
                        keyframe_id: torch.Tensor) -> GaussianRows:
        """Rows entering now: their entry geometry is their current one."""
        entry = {field: params[name].detach().clone() for field, name in ENTRY_GEOMETRY.items()}
        return cls(**{k: params[k] for k in PARAMETERS}, trackable=trackable, keyframe_id=keyframe_id, **entry)

    def entering_now(self) -> GaussianRows:
        """These rows with their current geometry as their entry geometry (new Gaussians made
        from others, e.g. a split's children)."""
        return GaussianRows.from_parameters(self.parameters(), self.trackable, self.keyframe_id)

    @classmethod
    def from_shapes(cls, means, quats, scales, colors, opacity, trackable, keyframe_id, device=None) -> GaussianRows:
        """From numpy arrays in natural units: scales (N,3) metres (clamped at 1e-8), opacity
        (N,) or a scalar in (0, 1), keyframe_id an int or (N,) ints."""
        n = len(means)
        opacity = np.broadcast_to(np.asarray(opacity, dtype=np.float64), (n,))

        def f32(a, width):
            return torch.as_tensor(np.asarray(a, dtype=np.float32), device=device).reshape((n, width) if width else n)

        params = {"means": f32(means, 3), "quats": f32(quats, 4),
                  "log_scales": f32(np.log(np.maximum(np.asarray(scales, dtype=np.float64), 1e-8)), 3),
                  "opacity_logits": f32(_logit(opacity), 0), "colors": f32(colors, 3)}
        return cls.from_parameters(
            params, trackable=torch.as_tensor(np.asarray(trackable, dtype=bool), device=device).reshape(n),
            keyframe_id=torch.as_tensor(np.broadcast_to(np.asarray(keyframe_id, dtype=np.int64), (n,)).copy(),
                                        device=device))

    @classmethod
    def from_covariances(cls, means, covariances, colors, opacity, trackable, keyframe_id, scale_factors=None,
                         device=None) -> GaussianRows:
        """From world covariances (N,3,3) m^2; each standard deviation optionally divided by
        `scale_factors` (N,) (the scale alignment of Gaussians entering the map)."""
        quats, scales = scales_from_covariance(np.asarray(covariances, dtype=np.float64))
        if scale_factors is not None:
            scales = scales / np.asarray(scale_factors, dtype=np.float64)[:, None]
        return cls.from_shapes(means, quats, scales, colors, opacity, trackable, keyframe_id, device)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def select(self, index) -> GaussianRows:
        """The rows at `index` (a bool mask or integer indices, numpy or torch)."""
        index = torch.as_tensor(np.asarray(index) if not isinstance(index, torch.Tensor) else index,
                                device=self.means.device)
        return GaussianRows(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def parameters(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in PARAMETERS}


def _leaf(t: torch.Tensor) -> torch.Tensor:
    """`t` as a new leaf tensor that autograd differentiates (the map's parameters)."""
    return t.detach().requires_grad_(True)


class GaussianMap:
    """3D Gaussians in world coordinates, stored as the 3DGS optimiser sees them.

    Parameters (float32 leaf tensors with requires_grad, one row per Gaussian; see PARAMETERS):
      means (N,3) metres; quats (N,4) (w, x, y, z), not necessarily unit (normalised where
      used); log_scales (N,3) log of standard deviations in metres; opacity_logits (N,) logit
      of opacity; colors (N,3) RGB in [0, 1] (SH degree 0).
    Per-Gaussian flags: trackable (N,) bool, keyframe_id (N,) int64 (the keyframe that added it).
    Entry geometry: entry_means, entry_quats, entry_log_scales, the values each Gaussian entered
    the map with, which no optimiser changes. The tracker aligns to them by default
    (`tracking_target(geometry="entry")`): the mapper reshapes and turns Gaussians for rendering
    (1-3 mm trackable Gaussians, smaller than a training pixel, have their normals turned by
    7-14 degrees median on TUM fr1/rpy), which cost 28% mean ATE when the tracker aligned to the
    optimised shapes (docs/tracking_under_mapping.md).

    Concurrency: whoever changes the map holds `lock`. Every change bumps `version`; removing or
    overwriting rows also bumps `structure_version` (appending does not), so a training step
    that started before can tell that its rows no longer hold the same Gaussians. Rows are
    appended only at the end. The tracker never reads the live tensors: it
    takes a `tracking_target()` copy under the lock, at a tracking keyframe.
    """

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.lock = threading.RLock()
        self.version = 0
        self.structure_version = 0
        empty = GaussianRows.from_shapes(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((0, 3)),
                                         0.5, np.zeros(0, bool), 0, self.device)
        self._set(empty)

    def _set(self, rows: GaussianRows) -> None:
        for f in fields(GaussianRows):
            value = getattr(rows, f.name)
            setattr(self, f.name, _leaf(value) if f.name in PARAMETERS else value)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> torch.Tensor:
        """(N,3) standard deviations in metres."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """(N,) opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    def parameters(self) -> dict[str, torch.Tensor]:
        """The optimisable leaf tensors by name (PARAMETERS order)."""
        return {name: getattr(self, name) for name in PARAMETERS}

    def _columns(self) -> dict[str, torch.Tensor]:
        """Every per-row tensor by GaussianRows field name (detached, not copied)."""
        return {f.name: getattr(self, f.name).detach() for f in fields(GaussianRows)}

    def rows(self, index=None) -> GaussianRows:
        """A detached copy of the rows at `index` (all rows when None)."""
        with self.lock:
            sel = slice(None) if index is None else index
            return GaussianRows(**{k: v[sel].clone() for k, v in self._columns().items()})

    def append(self, rows: GaussianRows) -> slice:
        """Add `rows` at the end; returns the rows they occupy."""
        with self.lock:
            start = len(self)
            merged = {k: torch.cat([v, getattr(rows, k).to(self.device)]) for k, v in self._columns().items()}
            self._set(GaussianRows(**merged))
            self.version += 1
        return slice(start, start + len(rows))

    def keep(self, mask: torch.Tensor) -> None:
        """Keep only the Gaussians where `mask` is true (the others are removed)."""
        with self.lock:
            mask = torch.as_tensor(mask, device=self.device)
            self._set(GaussianRows(**{k: v[mask] for k, v in self._columns().items()}))
            self.version += 1
            self.structure_version += 1

    def covariances(self) -> torch.Tensor:
        """(N,3,3) world-frame covariances R diag(s^2) R^T in m^2."""
        return covariance_from_scales(self.quats.detach(), self.scales.detach())

    def tracking_target(self, min_opacity: float = 0.0, geometry: str = "entry") -> TrackingTarget:
        """Copy the trackable Gaussians with opacity above `min_opacity` for a tracker, with their
        `geometry`: "entry" (means and shapes as they entered the map) or "optimised" (the
        mapper's current values, as the reference code)."""
        with self.lock:
            keep = self.trackable & (self.opacities.detach() > min_opacity)
            prefix = {"entry": "entry_", "optimised": ""}[geometry]
            means, quats, log_scales = (getattr(self, prefix + name).detach()[keep]
                                        for name in ("means", "quats", "log_scales"))
            cov = covariance_from_scales(quats, torch.exp(log_scales))
            return TrackingTarget(
                means=means.cpu().numpy().copy(), covariances=cov.cpu().numpy().copy(), version=self.version
            )


@dataclass
class TrackingTarget:
    """A read-only copy of the map Gaussians a tracker aligns to (world frame).

    means: Nx3 float32 metres. covariances: Nx3x3 float32 m^2 (raw, not regularised).
    version: the map version it was taken from.
    """

    means: np.ndarray
    covariances: np.ndarray
    version: int
