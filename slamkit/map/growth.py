"""How a keyframe's Gaussians enter the shared map (paper Sec. 3.1 "scale alignment").

A frame's Gaussians carry their raw k-NN covariance (`shape_covariances`; the regularised one
G-ICP aligns with has a median axis of 1 m and would make 10 cm - 1 m Gaussians). Entering the
map, each scale (square root of a raw eigenvalue) is divided by an alignment factor that grows with the point's
camera depth z (metres): none -> 1, constant -> c, z -> max(c z, 1), z_pow -> max(c z^p, 1)
(the paper's choice, p = 1.5; the default in sequential mode, with c = 1 where the reference
code has c = 2); eq4 -> Eq. 4 as printed, z^p dividing the ellipse-regularised scales (median
axis 1 m) in place of the raw ones. In real-time mode the
default is none: a Gaussian there gets a few dozen steps at most, and aligned scales (1-3 mm on
TUM, spaced ~1 cm) leave the views full of holes that the steps have no time to close (TUM
fr1/rpy real time 17.7 dB unaligned against 15.6 dB aligned; looped Replica 21.6 against 9.2
dB; docs/results.md). Sequential runs score higher the less they align (TUM fr1/rpy 18.23 /
18.38 / 18.53 / 18.60 dB for c = 2 / 1 / 0.5 / none; Replica room0 20 frames 27.63 / 28.30 /
28.83 / 28.90 dB), because the map bounded by the scene (`Strategy.admit`) keeps about one
Gaussian per sampling cell where the reference code piles every keyframe's on top of each other;
but their surfaces get blurrier (a mesh of the rendered depth of 20 Replica frames: median vertex
error 1.25 / 1.38 / 1.78 / 4.05 cm, 96 / 94 / 84 / 34 % of the true surface within 3 cm), so
c = 1 is the default: most of the PSNR, nearly the paper's surfaces (docs/results.md, "Scale
alignment with a bounded map"). Tracking hardly changes either way (TUM fr1/rpy 4.90 cm; 4.70
against 4.67 cm looped 4 times): the ellipse regularisation divides each target covariance
by its median eigenvalue, which cancels a Gaussian's alignment factor; only which trackable
Gaussians pruning removes (by opacity) depends on the training. Gaussians close to an existing
trackable map Gaussian (squared distance <= new_gaussian_overlap, m^2) are added for rendering
but not marked trackable, so the tracking target is not duplicated: the tracker measures the
distance to its target, and `new_gaussians` to the trackable Gaussians added since that target
was built (mapping-only keyframes'), which it lacks. Measured against the target alone, a
keyframe revisiting a mapping-only keyframe's view made its Gaussians trackable again, and
trackable Gaussians enter whatever the coverage test says: looped Replica room0 in real time
grew by ~5,700 Gaussians a mapping-only keyframe, to 180k for 20 frames (docs/results.md).
A mapping-only keyframe's Gaussians are never trackable (`mapping_only_trackable` false, the
paper's Sec. 3.3: they enter the map for rendering, not the tracking target), which measured as
good or better than making them trackable (docs/paper.md, "Differences"); `untargeted` then
matters only with `mapping_only_trackable=true`.

`new_gaussians` makes a keyframe's candidate rows; which of them enter the map is the mapper's
decision (`Mapper.admit`, in `slamkit.run.slam.SLAM`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from slamkit.config import PluginConfig, RunContext, require
from slamkit.geometry.gaussians import Regularization, regularize
from slamkit.map.gaussian_map import GaussianRows
from slamkit.types import FrameGaussians


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
    """initial_shape: gicp | knn (see InitialShape). scale_alignment: how gicp shapes are
    scaled entering the map (paper Table 6): none | constant | z | z_pow divide the raw k-NN
    scales by 1 | c | max(c z, 1) | max(c z^p, 1); eq4 (the paper's Eq. 4) divides the
    ellipse-regularised scales (median axis 1 m) by z^p; null: z_pow in sequential mode, none
    in real-time mode (see the module docstring). scale_c, scale_p: the c and p of max(c z^p, 1), p also Eq. 4's (the
    reference code: c = 2, p = 1.5; c = 1 by default, see the module docstring).
    initial_opacity: opacity of new Gaussians in (0, 1). new_gaussian_overlap: m^2, null = the
    dataset's (`DatasetTuning.new_gaussian_overlap`)."""

    initial_shape: InitialShape = InitialShape.gicp
    scale_alignment: ScaleAlignment | None = None
    scale_c: float = 1.0
    scale_p: float = 1.5
    initial_opacity: float = 0.1
    new_gaussian_overlap: float | None = None
    #: a mapping-only keyframe's Gaussians may become trackable (false: never, as the paper's Sec. 3.3; docs/paper.md)
    mapping_only_trackable: bool = False

    def validate(self) -> None:
        require(self.scale_c > 0, "growth.scale_c", "> 0", self.scale_c)
        require(self.scale_p >= 0, "growth.scale_p", ">= 0", self.scale_p)
        require(0 < self.initial_opacity < 1, "growth.initial_opacity", "in (0, 1)", self.initial_opacity)
        require(
            self.new_gaussian_overlap is None or self.new_gaussian_overlap >= 0,
            "growth.new_gaussian_overlap", "null or >= 0 m^2", self.new_gaussian_overlap,
        )

    def resolve(self, context: RunContext) -> MapGrowthConfig:
        """new_gaussian_overlap from the dataset's tuning; scale_alignment left null: none in
        real-time mode, z_pow otherwise."""
        return self.fill_nulls(new_gaussian_overlap=context.tuning.new_gaussian_overlap,
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
