"""Global registration: where a camera's points lie in a map, without a first guess.

Both clouds are voxel-downsampled (`voxel`, metres), given normals (radius 2 voxels) and FPFH
features (radius 5 voxels; Rusu et al. 2009); RANSAC over feature matches (3 points, mutual
matches, edge-length and distance checks, open3d's `registration_ransac_based_on_feature_matching`)
finds a coarse pose, which open3d's generalized ICP refines (distance 1 voxel). The map's
features are computed once. Needs open3d (the optional extra `mesh`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamkit.errors import SlamkitError

#: Normals and FPFH features use neighbours within these many voxels.
NORMAL_RADIUS_VOXELS = 2.0
FEATURE_RADIUS_VOXELS = 5.0
#: RANSAC's inlier distance, in voxels.
RANSAC_DISTANCE_VOXELS = 1.5


def import_open3d():
    """open3d, or a one-line SlamkitError saying how to install it."""
    try:
        import open3d
    except ImportError as exc:
        raise SlamkitError(f"open3d is not installed ({exc}); install it with pip install -e '.[mesh]'") from None
    return open3d


@dataclass
class Registration:
    """pose: 4x4 float64 taking the source points' frame to the target's (camera-to-world
    when the source is a camera's points and the target the map). fitness: the fraction of
    downsampled source points with a target point within one voxel after refinement.
    rmse_m: their RMS distance in metres."""

    pose: np.ndarray
    fitness: float
    rmse_m: float


class GlobalRegistration:
    """Registers point clouds against one target cloud (see the module docstring)."""

    def __init__(self, target_points: np.ndarray, voxel: float = 0.05, ransac_iterations: int = 100000,
                 ransac_confidence: float = 0.999):
        """target_points: (N,3) metres (e.g. the map's trackable Gaussian centres, world frame)."""
        self.o3d = import_open3d()
        self.voxel = float(voxel)
        self.ransac_iterations, self.ransac_confidence = int(ransac_iterations), float(ransac_confidence)
        self.target, self.target_features = self.features(target_points)

    def features(self, points: np.ndarray):
        """(downsampled open3d cloud with normals, its FPFH features) of (N,3) points in metres."""
        o3d = self.o3d
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
        cloud = cloud.voxel_down_sample(self.voxel)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_VOXELS * self.voxel,
                                                                    max_nn=30))
        features = o3d.pipelines.registration.compute_fpfh_feature(
            cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=FEATURE_RADIUS_VOXELS * self.voxel, max_nn=100))
        return cloud, features

    def register(self, points: np.ndarray, seed: int = 0) -> Registration:
        """The pose of (N,3) source points (metres) in the target's frame: FPFH + RANSAC (random
        choices from `seed`), then generalized ICP."""
        o3d = self.o3d
        reg = o3d.pipelines.registration
        source, features = self.features(points)
        o3d.utility.random.seed(int(seed))
        distance = RANSAC_DISTANCE_VOXELS * self.voxel
        coarse = reg.registration_ransac_based_on_feature_matching(
            source, self.target, features, self.target_features, True, distance,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
            reg.RANSACConvergenceCriteria(self.ransac_iterations, self.ransac_confidence))
        fine = reg.registration_generalized_icp(
            source, self.target, self.voxel, coarse.transformation,
            reg.TransformationEstimationForGeneralizedICP(), reg.ICPConvergenceCriteria(max_iteration=50))
        return Registration(np.asarray(fine.transformation, dtype=np.float64).copy(), float(fine.fitness),
                            float(fine.inlier_rmse))
