"""The G-ICP target: the map's trackable Gaussians the frames are aligned to (world frame, metres)."""

from __future__ import annotations

import numpy as np


class Target:
    """The aligned-to map Gaussians in the world frame: means (metres; float32 for the search and
    float64 for residuals), regularised covariances (m^2, float64), the map `version` they were
    taken at and the nearest-neighbour index over the means (built here, once per target, for
    searches within `max_distance` metres)."""

    def __init__(self, means: np.ndarray, covariances: np.ndarray, version: int, kernels, max_distance: float):
        self.means32 = np.ascontiguousarray(means, dtype=np.float32)
        # Means and covariances side by side: one gather per iteration.
        self.packed = np.concatenate([self.means32.astype(np.float64), covariances.reshape(-1, 9)], axis=1)
        self.version = version
        self.index = kernels.nearest_index(self.means32, max_distance)
        self._features = None  # global registration's view of the means, made when first needed

    def features(self, voxel: float):
        """The means ready for global registration (`slamkit.geometry.registration.FeatureCloud`,
        downsampled to `voxel` metres), made once per target: only a frame no alignment
        matched needs it."""
        if self._features is None:
            from slamkit.geometry.registration import FeatureCloud

            self._features = FeatureCloud(self.means, voxel)
        return self._features

    @property
    def means(self) -> np.ndarray:
        return self.packed[:, :3]

    @property
    def covariances(self) -> np.ndarray:
        return self.packed[:, 3:].reshape(-1, 3, 3)

    def __len__(self) -> int:
        return len(self.means)
