"""slamkit-p2plane: frame-to-model point-to-plane ICP, packaged as a third-party slamkit plugin.

How the plugin is wired (the whole of it; see docs/plugin_guide.md)
-------------------------------------------------------------------
1. `P2PlaneTracker` subclasses the role `slamkit.roles.Tracker`; slamkit builds it as
   ``P2PlaneTracker(config, context)`` and calls `track(frame)` (plus `initialize`, which gives
   the pose the trajectory starts from). It keeps its own model: the shared Gaussian map is
   offered through `update_target`, which it does not need.
2. `P2PlaneConfig` subclasses `slamkit.roles.PluginConfig`. slamkit stores this dataclass in
   Hydra's ConfigStore under the group ``tracker``, so ``tracker=p2plane tracker.knn=20`` is
   type-checked without any YAML, and `validate` rejects out-of-range values before any work.
   Fields left ``None`` are filled by `resolve` from the run's context, which holds the
   dataset's tuning (``pixel_stride`` from its ``tracking_pixel_stride``: 5 on TUM, 10 on Replica).
3. The hook `slamkit_plugins` returns ``PluginSpec("p2plane", P2PlaneTracker, P2PlaneConfig)``.
4. pyproject.toml names this module in the entry-point group ``slamkit``::

       [project.entry-points.slamkit]
       p2plane = "slamkit_p2plane"

   so ``pip install -e examples/slamkit-p2plane`` is all it takes for slamkit to find it.

The method
----------
Each frame's depth is back-projected on every `pixel_stride`-th pixel (camera frame, within
`max_range`). The model is the union of keyframe clouds in world coordinates, voxel-downsampled
to `voxel_size`, with one normal per point: the eigenvector of the smallest eigenvalue of its
`knn` nearest neighbours' covariance. Its KD-tree (pykdtree) and normals are rebuilt only when
a keyframe is added: a frame that moved more than `keyframe_translation` metres or
`keyframe_rotation_deg` degrees since the last keyframe.

The pose T (camera-to-world) starts from the constant-velocity guess and minimises

    sum_i rho(n_i . (T p_i - q_i))      q_i, n_i: the nearest model point of T p_i and its normal

over correspondences closer than `max_correspondence_distance` (rho: the Huber loss, as
reweighted least squares), by Gauss-Newton on SE(3): each step re-finds the correspondences
and solves for xi = (omega, v), the update T <- [so3_exp(omega) | v] T (a rotation about the
world origin, then a translation), whose residual Jacobian is (T p_i x n_i, n_i). A frame with
fewer than `min_correspondences` matches is lost.
The tracker ignores the shared GaussianMap (it keeps its own model), so use it with
``mapper=none``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from slamkit.geometry.gaussians import knn_covariances
from slamkit.geometry.transforms import (
    backproject,
    invert_pose,
    make_pose,
    nearest_rotation,
    rotation_angle_deg,
    so3_exp,
    transform_points,
)
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, RunContext, Tracker, require
from slamkit.types import Frame, TrackingResult


@dataclass
class P2PlaneConfig(PluginConfig):
    """Options of ``tracker=p2plane``, point-to-plane ICP against a voxelised model."""

    #: back-project every n-th pixel in x and y (null: the dataset's tracking_pixel_stride)
    pixel_stride: int | None = None
    #: metres; farther matches are ignored (null: the dataset's correspondence_distance)
    max_correspondence_distance: float | None = None
    #: metres, the model's downsampling grid
    voxel_size: float = 0.02
    #: neighbours of each model normal
    knn: int = 10
    #: metres; residuals beyond are down-weighted (Huber loss; 0: plain least squares)
    huber: float = 0.005
    #: Gauss-Newton steps per frame, at most
    max_iterations: int = 20
    #: converged when an update's norm (radians and metres) is below this
    tolerance: float = 3e-4
    #: metres moved since the last keyframe beyond which a frame is added to the model
    keyframe_translation: float = 0.05
    #: degrees turned since the last keyframe beyond which a frame is added to the model
    keyframe_rotation_deg: float = 10.0
    #: metres; farther points are not used (null: the dataset's depth_trunc)
    max_range: float | None = None
    #: fewer matches: the frame is lost and keeps the predicted pose
    min_correspondences: int = 100

    def validate(self) -> None:
        """Hydra has checked the types; check the ranges (a one-line ConfigError naming the field)."""
        checks = [
            ("pixel_stride", self.pixel_stride is None or self.pixel_stride >= 1, "null or an integer >= 1"),
            ("max_correspondence_distance",
             self.max_correspondence_distance is None or self.max_correspondence_distance > 0, "null or > 0 metres"),
            ("voxel_size", self.voxel_size > 0, "> 0 metres"),
            ("knn", self.knn >= 3, "an integer >= 3"),
            ("huber", self.huber >= 0, ">= 0 metres"),
            ("max_iterations", self.max_iterations >= 1, "an integer >= 1"),
            ("tolerance", self.tolerance > 0, "> 0"),
            ("keyframe_translation", self.keyframe_translation >= 0, ">= 0 metres"),
            ("keyframe_rotation_deg", self.keyframe_rotation_deg >= 0, ">= 0 degrees"),
            ("max_range", self.max_range is None or self.max_range > 0, "null or > 0 metres"),
            ("min_correspondences", self.min_correspondences >= 6, "an integer >= 6"),
        ]
        for name, ok, expected in checks:
            require(ok, f"tracker.{name}", expected, getattr(self, name))

    def resolve(self, context: RunContext) -> P2PlaneConfig:
        """The nulls filled from what the dataset knows of its camera (slamkit calls it)."""
        return self.fill_nulls(pixel_stride=context.tuning.tracking_pixel_stride,
                               max_correspondence_distance=context.tuning.correspondence_distance)


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """The first point of each occupied voxel (Nx3 in, Mx3 out, order kept)."""
    keys = np.floor(points / voxel_size).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


class Model:
    """Points in world coordinates (float64), their normals and a KD-tree over them."""

    def __init__(self, points: np.ndarray, knn: int):
        self.points = points
        self.tree = KDTree(points, leafsize=16)
        _, vectors = np.linalg.eigh(knn_covariances(points, knn, self.tree))  # ascending eigenvalues
        self.normals = vectors[:, :, 0]


def huber_weights(residual: np.ndarray, delta: float) -> np.ndarray:
    """Iteratively reweighted least squares weights of the Huber loss (1 within `delta`,
    delta / |r| beyond); all ones when delta is 0."""
    if delta == 0:
        return np.ones_like(residual)
    return np.minimum(1.0, delta / np.maximum(np.abs(residual), 1e-12))


def point_to_plane(model: Model, points: np.ndarray, pose: np.ndarray, max_distance: float, huber: float,
                   max_iterations: int, tolerance: float) -> tuple[np.ndarray, int, int]:
    """Align camera-frame `points` to `model` from `pose`. Returns (pose, correspondences of
    the last iteration, iterations run)."""
    matched = 0
    for iteration in range(1, max_iterations + 1):
        world = transform_points(pose, points)
        distance, index = model.tree.query(world, k=1, distance_upper_bound=max_distance)
        ok = np.isfinite(distance)
        matched = int(ok.sum())
        if matched < 6:
            break
        p, q, n = world[ok], model.points[index[ok]], model.normals[index[ok]]
        residual = np.einsum("ij,ij->i", n, p - q)
        J = np.hstack([np.cross(p, n), n])  # d residual / d (omega, v)
        Jw = J * huber_weights(residual, huber)[:, None]
        xi = np.linalg.solve(Jw.T @ J + 1e-9 * np.eye(6), -Jw.T @ residual)
        pose = make_pose(so3_exp(xi[:3]), xi[3:]) @ pose
        if np.linalg.norm(xi) < tolerance:
            break
    return make_pose(nearest_rotation(pose[:3, :3]), pose[:3, 3]), matched, iteration


class P2PlaneTracker(Tracker):
    """Frame-to-model point-to-plane ICP with a constant-velocity initial guess."""

    def __init__(self, cfg: P2PlaneConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        # slamkit filled the nulls from the dataset's tuning (`resolve`) before this
        require(cfg.pixel_stride is not None and cfg.max_correspondence_distance is not None, "tracker",
                "pixel_stride and max_correspondence_distance (P2PlaneConfig.resolve fills them)", cfg)
        self.pixel_stride = cfg.pixel_stride
        self.max_distance = cfg.max_correspondence_distance
        self.pose = np.eye(4)
        self.velocity = np.eye(4)  # the last frame-to-frame motion
        self.model: Model | None = None
        self.last_keyframe_pose: np.ndarray | None = None

    def initialize(self, first_pose: np.ndarray) -> None:
        self.pose = np.asarray(first_pose, dtype=np.float64).copy()

    def track(self, frame: Frame) -> TrackingResult:
        start = time.perf_counter()
        points, _ = backproject(frame.depth, frame.camera, self.pixel_stride)
        max_range = self.cfg.max_range if self.cfg.max_range is not None else frame.depth_trunc
        points = points[points[:, 2] <= max_range].astype(np.float64)
        predicted = self.pose @ self.velocity
        if self.model is None or len(points) < self.cfg.min_correspondences:  # first frame, or no depth
            pose, matched, iterations = predicted, len(points), 0
        else:
            c = self.cfg
            pose, matched, iterations = point_to_plane(self.model, points, predicted, self.max_distance, c.huber,
                                                       c.max_iterations, c.tolerance)
        lost = matched < self.cfg.min_correspondences or not np.all(np.isfinite(pose))
        if lost:
            pose = predicted
        elif self._is_keyframe(pose):
            self._add_keyframe(points, pose)
        self.velocity = invert_pose(self.pose) @ pose
        self.pose = pose
        stats = {"register_s": time.perf_counter() - start, "iterations": iterations, "correspondences": matched}
        if lost:
            stats["lost_reason"] = f"{matched} correspondences < {self.cfg.min_correspondences}"
        ratio = matched / len(points) if len(points) else 0.0
        return TrackingResult(pose=pose.copy(), lost=lost, correspondence_ratio=ratio, stats=stats)

    def _is_keyframe(self, pose: np.ndarray) -> bool:
        if self.last_keyframe_pose is None:
            return True
        motion = invert_pose(self.last_keyframe_pose) @ pose
        return (np.linalg.norm(motion[:3, 3]) > self.cfg.keyframe_translation
                or rotation_angle_deg(motion[:3, :3]) > self.cfg.keyframe_rotation_deg)

    def _add_keyframe(self, points: np.ndarray, pose: np.ndarray) -> None:
        """Merge the frame into the model; the only place the KD-tree and normals are built."""
        old = self.model.points if self.model is not None else np.zeros((0, 3))
        merged = voxel_downsample(np.concatenate([old, transform_points(pose, points)]), self.cfg.voxel_size)
        self.model = Model(merged, self.cfg.knn)
        self.last_keyframe_pose = pose.copy()


@hookimpl
def slamkit_plugins():
    return [PluginSpec("p2plane", P2PlaneTracker, P2PlaneConfig)]
