"""How a keyframe's Gaussians enter the shared map (paper Sec. 3.1 "scale alignment").

A frame's Gaussians carry their raw k-NN covariance (`shape_covariances`; the regularised one
G-ICP aligns with has a median axis of 1 m and would make 10 cm - 1 m Gaussians). Entering the
map, each scale (square root of a raw eigenvalue) is divided by an alignment factor that grows
with the point's camera depth z (metres): none -> 1, constant -> c, z -> max(c z, 1), z_pow ->
max(c z^p, 1) (the paper's choice, p = 1.5); eq4 -> Eq. 4 as printed, z^p dividing the
ellipse-regularised scales in place of the raw ones. The defaults: z_pow with c = 1 in
sequential mode (the reference code's c = 2 gives sharper surfaces but less PSNR), none in real
time (a Gaussian there gets a few dozen steps at most, too few to close the holes that small
aligned Gaussians leave); the measurements behind both are in docs/results.md ("Scale alignment")
and docs/paper.md. Tracking hardly depends on it: the ellipse
regularisation divides each target covariance by its median eigenvalue, which cancels a
Gaussian's alignment factor.

Gaussians within new_gaussian_overlap (squared distance, m^2) of an existing trackable map
Gaussian are added for rendering but not marked trackable, so the tracking target is not
duplicated: the tracker measures the distance to its target, and `new_gaussians` to the
trackable Gaussians added since that target was built (mapping-only keyframes'), which it lacks.
A mapping-only keyframe's Gaussians are never trackable unless `mapping_only_trackable` (the
paper's Sec. 3.3: they enter the map for rendering, not the tracking target); `untargeted` then
matters only with `mapping_only_trackable=true`.

A keyframe's Gaussians are the map's business, whatever the tracker: `frame_gaussians` makes them
from the frame's depth and colour at its tracked pose (every `pixel_stride`-th pixel, a k-NN
covariance per point as G-ICP's, the frame's colours). A tracker that made them anyway (G-ICP's
source Gaussians, which also carry the distance to its target) hands them over in
`TrackingResult.gaussians`, and they are used instead; both go through `gaussians_at_pose`, so the
two are the same formula. `new_gaussians` makes a keyframe's candidate rows; which of them enter
the map is the mapper's decision (`Mapper.admit`, in `slamkit.run.slam.SLAM`).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slamkit.config import PluginConfig, RunContext, method_setting, require
from slamkit.geometry.gaussians import Regularization, knn_covariances, regularize, rotate_covariances
from slamkit.geometry.transforms import backproject
from slamkit.map.gaussian_map import GaussianRows
from slamkit.types import Frame, FrameGaussians


class InitialShape(enum.Enum):
    """gicp: the tracker's covariance (rotation from its eigenvectors, scale-aligned).
    knn: 3DGS's usual initialisation, isotropic with scale = RMS distance to the 3 nearest
    other new points, identity rotation (paper Table 6, "w/o G-ICP covariance")."""

    gicp = "gicp"
    knn = "knn"


class ScaleAlignment(enum.Enum):
    """none, constant, z, z_pow: the raw k-NN scales divided by 1, c, max(c z, 1), max(c z^p, 1).
    eq4: the paper's Eq. 4, the ellipse-regularised scales (median axis 1 m) divided by z^p."""

    none = "none"
    constant = "constant"
    z = "z"
    z_pow = "z_pow"
    eq4 = "eq4"


@dataclass
class MapGrowthConfig(PluginConfig):
    """How keyframes grow the map (`growth.*`). Scale alignment (paper Table 6): none | constant |
    z | z_pow divide the raw k-NN scales by 1 | c | max(c z, 1) | max(c z^p, 1); eq4 (Eq. 4
    read literally) divides the ellipse-regularised scales (median axis 1 m) by z^p."""

    #: gicp | knn: new Gaussians' shapes (see InitialShape)
    initial_shape: InitialShape = method_setting(InitialShape.gicp)
    #: none | constant | z | z_pow | eq4 (null: z_pow sequential, none in real time; module docstring)
    scale_alignment: ScaleAlignment | None = method_setting(None)
    #: the c of max(c z^p, 1) (the reference code's 2; see the module docstring)
    scale_c: float = method_setting(1.0)
    #: the p of max(c z^p, 1) and of Eq. 4 (the reference code's 1.5)
    scale_p: float = method_setting(1.5)
    #: opacity of new Gaussians, in (0, 1)
    initial_opacity: float = 0.1
    #: m^2: a new Gaussian this close (squared) to a trackable one is not trackable (null: the dataset's)
    new_gaussian_overlap: float | None = None
    #: a mapping-only keyframe's Gaussians may become trackable (false: never, as the paper's Sec. 3.3; docs/paper.md)
    mapping_only_trackable: bool = method_setting(False)
    #: a keyframe's Gaussians from every n-th pixel when the tracker hands none (null: the dataset's tracking stride)
    pixel_stride: int | None = None
    #: neighbours (the point included) of a new Gaussian's k-NN covariance when the tracker hands none over
    knn: int = 10

    def validate(self) -> None:
        require(self.pixel_stride is None or self.pixel_stride >= 1,
                "growth.pixel_stride", "null or an integer >= 1", self.pixel_stride)
        require(self.knn >= 3, "growth.knn", "an integer >= 3", self.knn)
        require(self.scale_c > 0, "growth.scale_c", "> 0", self.scale_c)
        require(self.scale_p >= 0, "growth.scale_p", ">= 0", self.scale_p)
        require(0 < self.initial_opacity < 1, "growth.initial_opacity", "in (0, 1)", self.initial_opacity)
        require(
            self.new_gaussian_overlap is None or self.new_gaussian_overlap >= 0,
            "growth.new_gaussian_overlap", "null or >= 0 m^2", self.new_gaussian_overlap,
        )

    def resolve(self, context: RunContext) -> MapGrowthConfig:
        """new_gaussian_overlap and pixel_stride from the dataset's tuning; scale_alignment left
        null: none in real-time mode, z_pow otherwise."""
        return self.fill_nulls(new_gaussian_overlap=context.tuning.new_gaussian_overlap,
                               pixel_stride=context.tuning.tracking_pixel_stride,
                               scale_alignment=ScaleAlignment.none if context.realtime else ScaleAlignment.z_pow)


def scale_alignment_factors(depths: np.ndarray, cfg: MapGrowthConfig) -> np.ndarray:
    """Per-Gaussian divisors of the scales, from camera depths in metres (scale_alignment null:
    z_pow, as `resolve` outside real time)."""
    kind = cfg.scale_alignment or ScaleAlignment.z_pow
    if kind is ScaleAlignment.none:
        return np.ones_like(depths)
    if kind is ScaleAlignment.constant:
        return np.full_like(depths, cfg.scale_c)
    if kind is ScaleAlignment.eq4:
        return depths**cfg.scale_p
    p = 1.0 if kind is ScaleAlignment.z else cfg.scale_p
    return np.maximum(cfg.scale_c * depths**p, 1.0)


def knn_isotropic_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """(N,3) equal scales: the RMS distance (metres) of each point to its k nearest others."""
    from pykdtree.kdtree import KDTree

    pts = np.ascontiguousarray(points, dtype=np.float32)
    k = min(k + 1, len(pts))
    dist, _ = KDTree(pts).query(pts, k=k)
    dist = dist.reshape(len(pts), k)[:, 1:]
    rms = np.sqrt(np.mean(dist.astype(np.float64) ** 2, axis=1)) if k > 1 else np.full(len(pts), 0.01)
    return np.repeat(np.maximum(rms, 1e-4)[:, None], 3, axis=1)


def sq_dist_to_nearest(points: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(N,) squared distance (m^2) from each of `points` (N,3) to the nearest of `others` (P,3,
    P > 0), in float32."""
    from pykdtree.kdtree import KDTree

    query = np.ascontiguousarray(points, dtype=np.float32)
    dist, _ = KDTree(np.ascontiguousarray(others, dtype=np.float32)).query(query, k=1, sqr_dists=True)
    return dist.reshape(len(query))


def gaussians_at_pose(frame: Frame, pose: np.ndarray, points: np.ndarray, pix: np.ndarray, trackable: np.ndarray,
                      covariances: np.ndarray | Callable[[], np.ndarray], raw_covariances: np.ndarray,
                      sq_dist_to_map: np.ndarray | None) -> FrameGaussians:
    """The Gaussians of `frame`'s camera-frame points (N,3 metres, at flat pixel indices `pix`)
    placed at `pose` (camera-to-world): world means (m), `covariances` (the regularised ones a
    tracker aligns with, or a function making them) and `raw_covariances` (N,3,3 m^2, camera
    frame) rotated to the world, colours in [0, 1] from the frame's pixels, camera depths (m),
    `trackable` (N bool) and each point's squared distance (m^2) to the map, or None.
    Covariances and colours are computed when first read (Deferred): for keyframes only."""
    R, t = pose[:3, :3].copy(), pose[:3, 3].copy()  # kept by the deferred fields

    def colors() -> np.ndarray:
        rgb = np.asarray(frame.rgb).reshape(-1, 3)[pix]
        if np.issubdtype(rgb.dtype, np.integer):
            return rgb.astype(np.float32) / 255.0
        return np.clip(rgb, 0.0, 1.0).astype(np.float32)

    return FrameGaussians(
        means=(points.astype(np.float64) @ R.T + t).astype(np.float32),
        covariances=lambda: rotate_covariances(R, covariances() if callable(covariances) else covariances),
        shape_covariances=lambda: rotate_covariances(R, raw_covariances),
        colors=colors,
        depths=points[:, 2].copy(),
        trackable=trackable,
        sq_dist_to_map=sq_dist_to_map,
    )


def frame_gaussians(frame: Frame, pose: np.ndarray, cfg: MapGrowthConfig,
                    map_means: np.ndarray) -> FrameGaussians | None:
    """A keyframe's Gaussians made by the map's growth, for a tracker that hands none over: every
    `pixel_stride`-th pixel with valid depth back-projected and placed at `pose`
    (camera-to-world), its raw covariance from its `knn` nearest neighbours (regularised as
    G-ICP's `ellipse` for `covariances`), trackable within the frame's depth_trunc, and its
    squared distance (m^2) to the nearest of `map_means` ((P,3) world metres: the map's trackable
    Gaussians; inf when there are none). None when the frame has fewer valid points than `knn`."""
    depth = np.asarray(frame.depth)
    if not np.isfinite(depth).all():
        depth = np.where(np.isfinite(depth), depth, 0.0)
    points, pix = backproject(depth, frame.camera, int(cfg.pixel_stride or 1))
    if len(points) < cfg.knn:
        return None
    raw = knn_covariances(points, cfg.knn)
    trackable = points[:, 2] <= frame.depth_trunc
    gaussians = gaussians_at_pose(frame, np.asarray(pose, dtype=np.float64), points, pix, trackable,
                                  lambda: regularize(raw, Regularization.ellipse), raw, None)
    sq_dist = np.full(len(points), np.inf)
    if len(map_means) and trackable.any():
        sq_dist[trackable] = sq_dist_to_nearest(gaussians.means[trackable], map_means)
    gaussians.sq_dist_to_map = sq_dist
    return gaussians


def new_gaussians(gaussians: FrameGaussians, keyframe_id: int, cfg: MapGrowthConfig, device=None,
                  untargeted: np.ndarray | None = None, mapping_only: bool = False) -> GaussianRows:
    """A keyframe's Gaussians as map rows (scale-aligned, opacity `initial_opacity`), not yet in
    the map. Trackable are those the tracker found trackable whose squared distance (m^2) to
    its target (`sq_dist_to_map`) and to `untargeted` ((P,3) world metres: where the trackable
    map Gaussians its target does not hold yet entered the map) exceeds new_gaussian_overlap;
    none of a mapping-only keyframe's (`mapping_only`) unless `mapping_only_trackable`."""
    trackable = np.asarray(gaussians.trackable, dtype=bool)
    if mapping_only and not cfg.mapping_only_trackable:
        trackable = np.zeros_like(trackable)
    if gaussians.sq_dist_to_map is not None and cfg.new_gaussian_overlap is not None:
        trackable = trackable & (gaussians.sq_dist_to_map > cfg.new_gaussian_overlap)
        if untargeted is not None and len(untargeted) and trackable.any():
            rows = np.flatnonzero(trackable)
            sq_dist = sq_dist_to_nearest(np.asarray(gaussians.means)[rows], untargeted)
            trackable[rows] = sq_dist > cfg.new_gaussian_overlap
    if cfg.initial_shape is InitialShape.knn:
        quats = np.tile([1.0, 0.0, 0.0, 0.0], (len(gaussians), 1))
        return GaussianRows.from_shapes(gaussians.means, quats, knn_isotropic_scales(gaussians.means),
                                        gaussians.colors, cfg.initial_opacity, trackable, keyframe_id, device)

    def shapes() -> np.ndarray:  # called once the admitted rows' shapes are read (GaussianRows.from_covariances)
        raw = gaussians.shape_covariances
        raw = raw if raw is not None else gaussians.covariances
        eq4 = cfg.scale_alignment is ScaleAlignment.eq4
        return regularize(raw, Regularization.ellipse) if eq4 else raw

    return GaussianRows.from_covariances(
        gaussians.means, shapes, gaussians.colors, cfg.initial_opacity, trackable, keyframe_id,
        scale_factors=scale_alignment_factors(gaussians.depths.astype(np.float64), cfg), device=device,
    )
