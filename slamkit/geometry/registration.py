"""Global registration: where one point cloud lies in another's frame, without a first guess.

Both clouds are voxel-downsampled (`voxel`, metres), given normals (radius 2 voxels) and FPFH
features (radius 5 voxels; Rusu et al. 2009); RANSAC over feature matches (3 points, mutual
matches, edge-length and distance checks, open3d's `registration_ransac_based_on_feature_matching`)
finds a coarse pose, which open3d's generalized ICP refines (distance 1 voxel). Both run with
OpenMP pinned to one thread (`single_threaded`): open3d's RANSAC draws its random choices from
one seeded generator in whatever order its threads come, and G-ICP sums over threads in varying
order, so with threads the same two clouds give poses that differ from one call to the next
(in the last bits, or in the pose RANSAC kept), and a loop's decision near a threshold with them.
Pinned, the same clouds and seed give the same pose to the bit. A cloud's
features are computed once, when first needed (`FeatureCloud`), so that one cloud can be
registered with many.
Needs open3d (the optional extra `mesh`).

`alignment_information` is the information matrix of such an alignment, from its correspondences.
`refine_coloured` refines a pose with colour too (coloured ICP), for clouds given colours.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

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
    rmse_m: their RMS distance in metres. ransac_inliers: the feature matches RANSAC's coarse
    pose agreed with (within RANSAC_DISTANCE_VOXELS voxels)."""

    pose: np.ndarray
    fitness: float
    rmse_m: float
    ransac_inliers: int = 0


class FeatureCloud:
    """A point cloud ready for global registration: `cloud`, the open3d cloud voxel-downsampled
    (`voxel` metres) with normals (and the given covariances, averaged per voxel, which
    generalized ICP then uses in place of ones from the normals), and `features`, its FPFH
    features, computed on first use: most clouds of a loop closure are never registered (no
    candidate comes near them), and FPFH is the larger part of preparing one."""

    def __init__(self, points: np.ndarray, voxel: float, covariances: np.ndarray | None = None,
                 colours: np.ndarray | None = None):
        """points: (N,3) metres; covariances: (N,3,3) m^2 in the same frame, or None; colours:
        (N,3) RGB in [0, 1] (averaged per voxel, for `refine_coloured`), or None."""
        o3d = import_open3d()
        self.voxel = float(voxel)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
        if covariances is not None:
            cloud.covariances = o3d.utility.Matrix3dVector(np.asarray(covariances, dtype=np.float64))
        if colours is not None:
            cloud.colors = o3d.utility.Vector3dVector(np.asarray(colours, dtype=np.float64))
        cloud = cloud.voxel_down_sample(self.voxel)
        self.cloud: Any = cloud
        self._features: Any = None
        if len(cloud.points):  # a frame without valid depth has nothing to register
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_VOXELS * self.voxel,
                                                                        max_nn=30))

    @property
    def features(self) -> Any:
        """The cloud's FPFH features (open3d Feature, 33 x M), computed on first use."""
        if self._features is None:
            o3d = import_open3d()
            if len(self.cloud.points) == 0:
                self._features = o3d.pipelines.registration.Feature()
                self._features.resize(33, 0)
            else:
                self._features = o3d.pipelines.registration.compute_fpfh_feature(
                    self.cloud,
                    o3d.geometry.KDTreeSearchParamHybrid(radius=FEATURE_RADIUS_VOXELS * self.voxel, max_nn=100))
        return self._features

    def arrays(self) -> dict[str, np.ndarray]:
        """The cloud as arrays (points, normals, covariances and colours when it has them, FPFH
        features (33,M) when they were computed), from which `from_arrays` rebuilds it exactly
        (e.g. for a checkpoint)."""
        out = {"points": np.asarray(self.cloud.points).copy(), "normals": np.asarray(self.cloud.normals).copy()}
        if self._features is not None:
            out["features"] = np.asarray(self._features.data).copy()
        if self.cloud.has_covariances():
            out["covariances"] = np.asarray(self.cloud.covariances).copy()
        if self.cloud.has_colors():
            out["colours"] = np.asarray(self.cloud.colors).copy()
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], voxel: float) -> FeatureCloud:
        """The FeatureCloud whose `arrays()` these are (downsampled with `voxel` metres)."""
        o3d = import_open3d()
        self = cls.__new__(cls)
        self.voxel = float(voxel)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(arrays["points"], dtype=np.float64)))
        cloud.normals = o3d.utility.Vector3dVector(np.asarray(arrays["normals"], dtype=np.float64))
        if "covariances" in arrays:
            cloud.covariances = o3d.utility.Matrix3dVector(np.asarray(arrays["covariances"], dtype=np.float64))
        if "colours" in arrays:
            cloud.colors = o3d.utility.Vector3dVector(np.asarray(arrays["colours"], dtype=np.float64))
        self.cloud = cloud
        self._features = None
        if "features" in arrays:
            self._features = o3d.pipelines.registration.Feature()
            self._features.data = np.asarray(arrays["features"], dtype=np.float64)
        return self

    @property
    def points(self) -> np.ndarray:
        """(M,3) float64 metres: the downsampled points."""
        return np.asarray(self.cloud.points)

    def __len__(self) -> int:
        return len(self.cloud.points)


_THREADPOOLS: Any = None


def single_threaded():
    """A context in which OpenMP (open3d's) runs on one thread in the calling thread, so that
    open3d's registration is deterministic (see the module docstring)."""
    global _THREADPOOLS
    if _THREADPOOLS is None:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError as exc:
            raise SlamkitError(f"threadpoolctl is not installed ({exc}); install it with pip install -e '.[loop]'") \
                from None
        _THREADPOOLS = ThreadpoolController()  # finds the loaded OpenMP runtimes once (open3d's among them)
    return _THREADPOOLS.limit(limits=1, user_api="openmp")


def register(source: FeatureCloud, target: FeatureCloud, ransac_iterations: int = 100000,
             ransac_confidence: float = 0.999, seed: int = 0, refine_iterations: int = 50) -> Registration:
    """The pose of `source` in `target`'s frame: FPFH + RANSAC (random choices from `seed`),
    then generalized ICP; distances in units of `target.voxel`. Identity with fitness 0 when
    either cloud is empty. Deterministic: the same clouds and seed give the same result."""
    if len(source) == 0 or len(target) == 0:
        return Registration(np.eye(4), 0.0, 0.0, 0)
    o3d = import_open3d()
    _ = source.features, target.features  # computed here, threaded: per point, the same on any thread count
    with single_threaded():
        return _register(o3d, source, target, ransac_iterations, ransac_confidence, seed, refine_iterations)


def _register(o3d, source: FeatureCloud, target: FeatureCloud, ransac_iterations: int, ransac_confidence: float,
              seed: int, refine_iterations: int) -> Registration:
    reg = o3d.pipelines.registration
    voxel = target.voxel
    o3d.utility.random.seed(int(seed))
    distance = RANSAC_DISTANCE_VOXELS * voxel
    coarse = reg.registration_ransac_based_on_feature_matching(
        source.cloud, target.cloud, source.features, target.features, True, distance,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(int(ransac_iterations), float(ransac_confidence)))
    fine = _refine(o3d, source, target, coarse.transformation, refine_iterations)
    return replace(fine, ransac_inliers=len(coarse.correspondence_set))


def refine(source: FeatureCloud, target: FeatureCloud, initial: np.ndarray, iterations: int = 50,
           max_distance: float | None = None) -> Registration:
    """The pose of `source` in `target`'s frame by generalized ICP alone, from `initial` (4x4);
    correspondences within `max_distance` metres (None: 1 voxel of `target`, which also bounds
    how far from `initial` it can pull the pose); ransac_inliers 0. Deterministic, as `register`."""
    if len(source) == 0 or len(target) == 0:
        return Registration(np.asarray(initial, dtype=np.float64).copy(), 0.0, 0.0, 0)
    o3d = import_open3d()
    with single_threaded():
        return _refine(o3d, source, target, initial, iterations, max_distance)


def _refine(o3d, source: FeatureCloud, target: FeatureCloud, initial: np.ndarray, iterations: int,
            max_distance: float | None = None) -> Registration:
    reg = o3d.pipelines.registration
    fine = reg.registration_generalized_icp(
        source.cloud, target.cloud, target.voxel if max_distance is None else max_distance,
        np.asarray(initial, dtype=np.float64),
        reg.TransformationEstimationForGeneralizedICP(), reg.ICPConvergenceCriteria(max_iteration=iterations))
    return Registration(np.asarray(fine.transformation, dtype=np.float64).copy(), float(fine.fitness),
                        float(fine.inlier_rmse))


def refine_coloured(source: FeatureCloud, target: FeatureCloud, initial: np.ndarray,
                    scales: tuple[float, ...] = (2.0, 1.0), iterations: int = 50) -> np.ndarray:
    """The pose (4x4) of `source` in `target`'s frame by coloured ICP (Park, Zhou and Koltun
    2017, open3d's: point-to-plane and the colour's gradient on the tangent plane, weighted 0.968
    to 0.032) from `initial`, coarse to fine: correspondences within each of `scales` voxels of
    `target` in turn, each from the last's pose; a scale that matches nothing keeps the pose so
    far. Both clouds need colours. Deterministic, as `register`."""
    pose = np.asarray(initial, dtype=np.float64).copy()
    if len(source) == 0 or len(target) == 0:
        return pose
    if not (source.cloud.has_colors() and target.cloud.has_colors()):
        raise ValueError("refine_coloured: both clouds need colours (FeatureCloud(..., colours=))")
    reg = import_open3d().pipelines.registration
    with single_threaded():
        for scale in scales:
            try:
                pose = np.asarray(reg.registration_colored_icp(
                    source.cloud, target.cloud, scale * target.voxel, pose, reg.TransformationEstimationForColoredICP(),
                    reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                               max_iteration=iterations)).transformation, dtype=np.float64).copy()
            except RuntimeError:  # "No correspondences found": nothing within this scale
                pass
    return pose


def alignment_information(source: FeatureCloud, target: FeatureCloud, pose: np.ndarray,
                          max_distance: float) -> tuple[np.ndarray, int]:
    """The point-to-plane information of `source` aligned to `target` by `pose` (source frame to
    target frame): (6x6, (rotation rad, translation m) order, for a small motion exp(xi) of the
    source's frame; the number of matched points). Each downsampled source point with a target
    point within `max_distance` metres (the nearest) adds J^T J, J = n^T [-skew(p) | I], p the
    source point and n the target point's normal, both in the source frame: the Gauss-Newton
    Hessian of point-to-plane ICP at `pose`, per unit residual variance. A direction the scene
    does not constrain (sliding along a wall) has a small eigenvalue."""
    from pykdtree.kdtree import KDTree

    if len(source) == 0 or len(target) == 0:
        return np.zeros((6, 6)), 0
    pose = np.asarray(pose, dtype=np.float64)
    p = source.points
    tree = KDTree(target.points)
    distance, nearest = tree.query(p @ pose[:3, :3].T + pose[:3, 3], k=1, distance_upper_bound=max_distance)
    matched = np.isfinite(distance) & (nearest < len(target))
    p = p[matched]
    n = np.asarray(target.cloud.normals)[nearest[matched]] @ pose[:3, :3]  # rows: R^T n, in the source frame
    J = np.concatenate([np.cross(p, n), n], axis=1)  # n^T [-skew(p) | I] = [(p x n)^T, n^T]
    return J.T @ J, int(matched.sum())


class GlobalRegistration:
    """Registers point clouds against one target cloud (see the module docstring)."""

    def __init__(self, target_points: np.ndarray, voxel: float = 0.05, ransac_iterations: int = 100000,
                 ransac_confidence: float = 0.999):
        """target_points: (N,3) metres (e.g. the map's trackable Gaussian centres, world frame)."""
        self.voxel = float(voxel)
        self.ransac_iterations, self.ransac_confidence = int(ransac_iterations), float(ransac_confidence)
        self.target = FeatureCloud(target_points, self.voxel)

    def register(self, points: np.ndarray, seed: int = 0) -> Registration:
        """The pose of (N,3) source points (metres) in the target's frame: FPFH + RANSAC (random
        choices from `seed`), then generalized ICP."""
        return register(FeatureCloud(points, self.voxel), self.target, self.ransac_iterations,
                        self.ransac_confidence, seed)
