"""Tiny mapping scenes and a 3DGS trainer built from its parts, for the trainer and parts tests.

Scenes are 40x30 pixels with a few hundred Gaussians, so whole training runs take seconds."""

from __future__ import annotations

import numpy as np
import torch

from slamkit.config import RunContext
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.registry.discovery import default_registry
from slamkit.roles import Tracker
from slamkit.tuning import DatasetTuning
from slamkit.types import Camera, Frame, FrameGaussians, KeyframeKind, TrackingResult

CAM = Camera(40, 30, 30.0, 30.0, 19.5, 14.5)
N = 300


def plane_scene(seed: int = 0, opacity: float = 0.9, n: int = N):
    """Gaussians on the plane z = 2 m in front of the identity camera, random colours."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([-1.5, -1.1], [1.5, 1.1], size=(n, 2))
    means = np.c_[xy, np.full(n, 2.0)].astype(np.float32)
    quats = np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32)
    scales = np.tile([0.08, 0.08, 0.01], (n, 1)).astype(np.float32)
    colors = rng.uniform(size=(n, 3)).astype(np.float32)
    return means, quats, scales, colors, opacity


def rows(means, quats, scales, colors, opacity, keyframe_id: int = 0) -> GaussianRows:
    return GaussianRows.from_shapes(means, quats, scales, colors, opacity, np.ones(len(means), bool), keyframe_id)


def make_map(means, quats, scales, colors, opacity, keyframe_id: int = 0) -> GaussianMap:
    gm = GaussianMap()
    gm.append(rows(means, quats, scales, colors, opacity, keyframe_id))
    return gm


def pose_x(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def render_frame(rasterizer, gm: GaussianMap, pose: np.ndarray, index: int = 0) -> Frame:
    """A frame rendered from `gm`: rgb uint8, depth = expected depth where alpha > 0.5."""
    w2c = torch.as_tensor(np.linalg.inv(pose), dtype=torch.float32)
    with torch.no_grad():
        out = rasterizer.render(gm.means, gm.quats, gm.scales, gm.opacities, gm.colors, w2c, CAM)
    rgb = (out.color.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    alpha = out.alpha.numpy()
    depth = np.where(alpha > 0.5, out.depth.numpy() / np.maximum(alpha, 1e-6), 0).astype(np.float32)
    return Frame(index, float(index), rgb, depth, CAM, pose)


def start_map(seed: int = 1) -> GaussianMap:
    """The scene's geometry, slightly perturbed, grey, opacity 0.1 (as new Gaussians enter)."""
    means, quats, scales, _, _ = plane_scene()
    rng = np.random.default_rng(seed)
    means = means + rng.normal(0, 0.01, means.shape).astype(np.float32)
    return make_map(means, quats, scales * 1.2, np.full((len(means), 3), 0.5, np.float32), 0.1)


PART_DEFAULTS = {"rasterizer": "torch", "sampler": "random", "strategy": "gsicp", "optimizer": "adam",
                 "loss": "l1_ssim_depth"}


def make_mapper(gm: GaussianMap | None = None, tuning: DatasetTuning | None = None, **settings):
    """A `gaussian_splatting` mapper (a trainer: it holds the parts) built through the registry,
    on `gm` (default `start_map()`). `settings`: `mapper={...}` (the mapper's config fields; training
    at full resolution unless given), and per part either a plugin name, or (name, {field: value}),
    e.g. `strategy=("3dgs", {"densify_every": 3})`."""
    registry = default_registry()
    gm = gm if gm is not None else start_map()
    context = RunContext(tuning=tuning or DatasetTuning(), gaussian_map=gm, build=registry.create)
    parts = {}
    for role, default in PART_DEFAULTS.items():
        name, fields = _choice(settings.pop(role, default))
        parts[role] = registry.create(role, name, registry.get(role, name).config(**fields), context)
    mapper_fields = {"resolution_scale": 1.0, **settings.pop("mapper", {})}
    assert not settings, f"unknown settings {settings}"
    spec = registry.get("mapper", "gaussian_splatting")
    return registry.create("mapper", "gaussian_splatting", spec.config(**mapper_fields), context, **parts)


def _choice(value):
    return (value, {}) if isinstance(value, str) else value


def add(mapper, frame: Frame, kind: KeyframeKind = KeyframeKind.TRACKING, new_rows: slice | None = None) -> None:
    """Register `frame` as a keyframe at its ground-truth pose (its Gaussians, if any, already at
    `new_rows`)."""
    n = len(mapper.gaussian_map)
    mapper.add_keyframe(frame, frame.gt_pose, kind, new_rows if new_rows is not None else slice(n, n))


def state_follows_map(mapper) -> None:
    """The optimiser's and the strategy's per-row state cover exactly the map's rows, and the
    map's parameters are leaves autograd differentiates."""
    n = len(mapper.gaussian_map)
    for name, tensors in mapper.optimizer.row_state().items():
        assert all(t.shape[0] == n for t in tensors), name
    for name, t in mapper.strategy.state.items():
        assert t.shape[0] == n, name
    for name, p in mapper.gaussian_map.parameters().items():
        assert p.is_leaf and p.requires_grad, name


class GroundTruthTracker(Tracker):
    """Reports each frame's ground-truth pose with Gaussians from its depth; records the
    tracking target it is given at each tracking keyframe."""

    def __init__(self, stride: int = 3, geometry: str = "entry"):
        self.stride, self.geometry = stride, geometry
        self.targets = []

    def track(self, frame):
        v, u = np.mgrid[0 : CAM.height : self.stride, 0 : CAM.width : self.stride]
        v, u = v.ravel(), u.ravel()
        z = frame.depth[v, u]
        keep = z > 0
        v, u, z = v[keep], u[keep], z[keep]
        pts = np.stack([(u - CAM.cx) / CAM.fx * z, (v - CAM.cy) / CAM.fy * z, z], 1)
        world = pts @ frame.gt_pose[:3, :3].T + frame.gt_pose[:3, 3]
        cov = np.tile(np.diag([1.0, 1.0, 0.01]), (len(z), 1, 1))
        g = FrameGaussians(world, cov, frame.rgb[v, u] / 255.0, z, np.ones(len(z), bool))
        return TrackingResult(frame.gt_pose, gaussians=g)

    def update_target(self, gaussian_map):
        self.targets.append(gaussian_map.tracking_target(geometry=self.geometry))
