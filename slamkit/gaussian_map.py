"""The Gaussian map shared by tracking and mapping."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import torch

from slamkit.geometry import covariance_from_scales, scales_from_covariance

_PARAMS = ("means", "quats", "log_scales", "opacity_logits", "colors")


@dataclass
class TrackingTarget:
    """A read-only copy of the map Gaussians a tracker aligns to (world frame).

    means: Nx3 float32 metres. covariances: Nx3x3 float32 m^2 (raw, not regularised).
    version: the map version it was taken from.
    """

    means: np.ndarray
    covariances: np.ndarray
    version: int


class GaussianMap:
    """3D Gaussians in world coordinates, stored as the 3DGS optimiser sees them.

    Parameters (torch float32 tensors, one row per Gaussian):
      means (N,3) metres; quats (N,4) (w, x, y, z), not necessarily unit (normalised where
      used); log_scales (N,3) log of standard deviations in metres; opacity_logits (N,)
      logit of opacity; colors (N,3) RGB in [0, 1] (SH degree 0).
    Per-Gaussian flags (torch): trackable (N,) bool, keyframe_id (N,) int64 (the keyframe that
    added it).

    Concurrency: the mapper changes parameters only while holding `lock`; every structural
    change or optimiser step bumps `version`. The tracker never reads the live tensors: it
    takes a `tracking_target()` copy under the lock, and only at a tracking keyframe.
    """

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.lock = threading.RLock()
        self.version = 0
        self.means = torch.zeros((0, 3), device=self.device)
        self.quats = torch.zeros((0, 4), device=self.device)
        self.log_scales = torch.zeros((0, 3), device=self.device)
        self.opacity_logits = torch.zeros((0,), device=self.device)
        self.colors = torch.zeros((0, 3), device=self.device)
        self.trackable = torch.zeros((0,), dtype=torch.bool, device=self.device)
        self.keyframe_id = torch.zeros((0,), dtype=torch.int64, device=self.device)

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
        """The optimisable tensors by name."""
        return {name: getattr(self, name) for name in _PARAMS}

    def append(
        self,
        means: np.ndarray,
        quats: np.ndarray,
        scales: np.ndarray,
        colors: np.ndarray,
        opacity: float | np.ndarray,
        trackable: np.ndarray,
        keyframe_id: int,
    ) -> slice:
        """Add Gaussians (world frame, scales in metres, opacity in (0,1)); returns their rows."""
        n = len(means)
        opacity = np.broadcast_to(np.asarray(opacity, dtype=np.float32), (n,))
        new = {
            "means": means,
            "quats": quats,
            "log_scales": np.log(np.maximum(scales, 1e-8)),
            "opacity_logits": np.log(opacity / (1 - opacity)),
            "colors": colors,
        }
        with self.lock:
            start = len(self)
            for name, value in new.items():
                t = torch.as_tensor(np.asarray(value, dtype=np.float32), device=self.device)
                setattr(self, name, torch.cat([getattr(self, name).detach(), t]))
            self.trackable = torch.cat(
                [self.trackable, torch.as_tensor(np.asarray(trackable, dtype=bool), device=self.device)]
            )
            self.keyframe_id = torch.cat(
                [self.keyframe_id, torch.full((n,), keyframe_id, dtype=torch.int64, device=self.device)]
            )
            self.version += 1
        return slice(start, start + n)

    def append_covariances(
        self, means, covariances, colors, opacity, trackable, keyframe_id, scale_factors=None
    ) -> slice:
        """Add Gaussians given as covariances (Nx3x3, m^2), each scale optionally divided by
        `scale_factors` (N,) (the scale alignment of Gaussians entering the map)."""
        quats, scales = scales_from_covariance(np.asarray(covariances, dtype=np.float64))
        if scale_factors is not None:
            scales = scales / np.asarray(scale_factors)[:, None]
        return self.append(means, quats, scales, colors, opacity, trackable, keyframe_id)

    def keep(self, mask: torch.Tensor) -> None:
        """Keep only the Gaussians where `mask` is true (pruning)."""
        with self.lock:
            for name in _PARAMS + ("trackable", "keyframe_id"):
                setattr(self, name, getattr(self, name).detach()[mask])
            self.version += 1

    def covariances(self) -> torch.Tensor:
        """(N,3,3) world-frame covariances R diag(s^2) R^T in m^2."""
        return covariance_from_scales(self.quats.detach(), self.scales.detach())

    def tracking_target(self, min_opacity: float = 0.0) -> TrackingTarget:
        """Copy the trackable Gaussians with opacity above `min_opacity` for a tracker."""
        with self.lock:
            keep = self.trackable & (self.opacities.detach() > min_opacity)
            means = self.means.detach()[keep]
            cov = covariance_from_scales(self.quats.detach()[keep], torch.exp(self.log_scales.detach()[keep]))
            return TrackingTarget(
                means=means.cpu().numpy().copy(), covariances=cov.cpu().numpy().copy(), version=self.version
            )
