"""The 3DGS mapper (`mapper=gaussian_splatting`), its keyframe samplers and image metrics.

Scenes are tiny (40x30 pixels, a few hundred Gaussians) so the whole file runs in seconds."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from pytorch_msssim import ssim as ms_ssim

from slamkit import image_metrics
from slamkit.errors import ConfigError, PluginError
from slamkit.gaussian_map import GaussianMap
from slamkit.map_growth import MapGrowthConfig
from slamkit.ply import load_ply
from slamkit.registry import create_rasterizer, default_registry
from slamkit.roles import Tracker
from slamkit.slam import SLAM
from slamkit.types import Camera, Frame, FrameGaussians, KeyframeKind, TrackingResult
from slamkit_plugins.keyframes.every_n import EveryNKeyframeConfig, EveryNKeyframePolicy
from slamkit_plugins.mappers.gaussian_splatting import (
    GaussianSplattingConfig,
    GaussianSplattingMapper,
    resize_rgbd,
)
from slamkit_plugins.samplers.keyframe_samplers import CovisibleSampler, RandomSampler, RecentSampler

CAM = Camera(40, 30, 30.0, 30.0, 19.5, 14.5)
N = 300


@pytest.fixture(scope="module")
def rasterizer():
    return create_rasterizer("torch")


def plane_scene(seed: int = 0, opacity: float = 0.9, n: int = N):
    """Gaussians on the plane z = 2 m in front of the identity camera, random colours."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([-1.5, -1.1], [1.5, 1.1], size=(n, 2))
    means = np.c_[xy, np.full(n, 2.0)].astype(np.float32)
    quats = np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32)
    scales = np.tile([0.08, 0.08, 0.01], (n, 1)).astype(np.float32)
    colors = rng.uniform(size=(n, 3)).astype(np.float32)
    return means, quats, scales, colors, opacity


def make_map(means, quats, scales, colors, opacity) -> GaussianMap:
    gm = GaussianMap()
    gm.append(means, quats, scales, colors, opacity, np.ones(len(means), bool), 0)
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


@pytest.fixture(scope="module")
def truth_frames(rasterizer):
    truth = make_map(*plane_scene())
    return [render_frame(rasterizer, truth, pose_x(x), i) for i, x in enumerate((0.0, 0.15))]


def start_map(seed: int = 1) -> GaussianMap:
    """The scene's geometry, slightly perturbed, grey, opacity 0.1 (as new Gaussians enter)."""
    means, quats, scales, _, _ = plane_scene()
    rng = np.random.default_rng(seed)
    means = means + rng.normal(0, 0.01, means.shape).astype(np.float32)
    return make_map(means, quats, scales * 1.2, np.full((len(means), 3), 0.5, np.float32), 0.1)


def make_mapper(rasterizer, gm: GaussianMap | None = None, **overrides) -> GaussianSplattingMapper:
    overrides.setdefault("final_iterations", 5)
    cfg = GaussianSplattingConfig(resolution_scale=1.0, **overrides)
    mapper = GaussianSplattingMapper(cfg, rasterizer=rasterizer, sampler=RandomSampler())
    mapper.bind(gm if gm is not None else start_map())
    return mapper


def add(mapper, frame, kind=KeyframeKind.TRACKING, rows=None):
    rows = rows if rows is not None else slice(len(mapper.gaussian_map), len(mapper.gaussian_map))
    mapper.add_keyframe(frame, TrackingResult(frame.gt_pose), kind, rows)


def adam_consistent(mapper) -> None:
    n = len(mapper.gaussian_map)
    assert len(mapper._adam) == n
    for name, p in mapper.gaussian_map.parameters().items():
        assert p.is_leaf and p.requires_grad, name
        assert mapper._adam.m[name].shape == p.shape and mapper._adam.v[name].shape == p.shape


# -- image metrics -------------------------------------------------------------------------


def test_psnr_ssim_l1_and_masks():
    rng = np.random.default_rng(0)
    a = torch.as_tensor(rng.uniform(size=(20, 24, 3)), dtype=torch.float32)
    b = a.clone()
    assert image_metrics.psnr(a, b) == math.inf
    assert image_metrics.ssim(a, b) == pytest.approx(1.0, abs=1e-6)
    b += 0.1
    assert image_metrics.psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    mask = torch.zeros(20, 24, dtype=torch.bool)
    mask[:, :12] = True
    b[:, 12:] = 0.9  # outside the mask: does not count
    assert image_metrics.psnr(a, b, mask) == pytest.approx(20.0, abs=1e-4)
    # masked SSIM = SSIM of both images with the outside pixels zeroed (the reference's way)
    m = mask[..., None].float()
    expected = ms_ssim((a * m).permute(2, 0, 1)[None], (b * m).permute(2, 0, 1)[None], data_range=1.0)
    assert image_metrics.ssim(a, b, mask) == pytest.approx(float(expected), abs=1e-6)
    d_obs = torch.full((20, 24), 2.0)
    d_obs[0] = 0  # invalid
    d_ren = torch.full((20, 24), 2.05)
    d_ren[0] = 100.0
    assert image_metrics.l1_depth(d_ren, d_obs) == pytest.approx(0.05, abs=1e-6)
    assert math.isnan(image_metrics.psnr(a, b, torch.zeros_like(mask)))


def test_resize_keeps_depth_validity():
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[:, 4:] = 255
    depth = np.full((8, 8), 2.0, np.float32)
    depth[:4, :4] = 0  # a quarter invalid
    depth[:2, 4:6] = 0  # 1/4 of one output pixel's area
    image, d, cam = resize_rgbd(rgb, depth, Camera(8, 8, 10, 10, 3.5, 3.5), 0.25)
    assert image.shape == (2, 2, 3) and cam.width == 2 and cam.cx == pytest.approx(0.5)
    torch.testing.assert_close(image[:, :, 0], torch.tensor([[0.0, 1.0], [0.0, 1.0]]))
    torch.testing.assert_close(d, torch.tensor([[0.0, 2.0], [2.0, 2.0]]))  # mean of valid pixels only


# -- samplers ------------------------------------------------------------------------------


def look(yaw_deg: float, x: float = 0.0) -> np.ndarray:
    a = math.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    T[0, 3] = x
    return T


def test_samplers_choices(caplog):
    rng = np.random.default_rng(0)
    ids = [3, 4, 5, 6, 7]
    counts = np.bincount([RandomSampler().sample(ids, None, rng) for _ in range(2000)], minlength=8)[3:]
    assert counts.min() > 300 and counts.max() < 500  # uniform: 400 each
    assert RecentSampler().sample(ids, None, rng) == 7
    poses = {0: look(0), 1: look(180), 2: look(5, 0.1), 3: look(170), 4: look(-5), 5: look(90)}
    sampler = CovisibleSampler()
    scores = sampler.scores(look(0), [poses[k] for k in range(6)])
    assert scores[0] == pytest.approx(1.0) and scores[1] == 0 and scores[3] == 0
    chosen = {sampler.sample(list(poses), look(0), rng, keyframe_poses=poses) for _ in range(200)}
    assert chosen == {0, 2, 4}  # the three looking the same way, each drawn
    with caplog.at_level(logging.WARNING):
        assert sampler.sample([1, 2], look(0), rng) in (1, 2)  # no poses: uniform, with a warning
    assert "no keyframe poses" in caplog.text
    with pytest.raises(ValueError):
        RandomSampler().sample([], None, rng)


def test_built_through_the_registry():
    registry = default_registry()
    assert {"random", "covisible", "recent"} <= set(registry.plugins["sampler"])
    cfg = GaussianSplattingConfig(rasterizer="torch", sampler="covisible")
    mapper = registry.create("mapper", "gaussian_splatting", cfg)
    assert isinstance(mapper.sampler, CovisibleSampler) and mapper._sampler_takes_poses
    with pytest.raises(PluginError, match="covisible"):
        GaussianSplattingMapper(GaussianSplattingConfig(rasterizer="torch", sampler="nope"))
    with pytest.raises(ConfigError, match="mapper.resolution_scale"):
        GaussianSplattingConfig(resolution_scale=0)
    with pytest.raises(ConfigError, match="mapper.max_scale"):
        GaussianSplattingConfig(max_scale=-1.0)


# -- training ------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_training_one_view_lowers_loss_and_raises_psnr(rasterizer, truth_frames, backend):
    frame = truth_frames[0]
    mapper = make_mapper(rasterizer if backend == "torch" else create_rasterizer(backend))
    before = mapper.evaluate([frame], [frame.gt_pose], None)["psnr"]
    add(mapper, frame)
    assert mapper.optimize(1) == 1  # the new keyframe, once on arrival
    first = mapper.last_loss
    version = mapper.gaussian_map.version
    assert mapper.optimize(80) == 80
    assert mapper.gaussian_map.version == version + 80  # bumped after every step
    assert mapper.last_loss < 0.6 * first
    metrics = mapper.evaluate([frame], [frame.gt_pose], None)
    assert metrics["psnr"] > before + 5 and metrics["psnr_train"] == metrics["psnr"]
    assert metrics["psnr_test"] is None and metrics["num_gaussians"] == N
    adam_consistent(mapper)


def test_new_keyframe_trained_first_then_sampled(rasterizer, truth_frames):
    mapper = make_mapper(rasterizer)
    trained = []
    step = mapper.train_step
    mapper.train_step = lambda kf: trained.append(kf.id) or step(kf)
    add(mapper, truth_frames[0])
    add(mapper, truth_frames[1], KeyframeKind.MAPPING_ONLY)
    assert mapper.optimize(0) == 0
    mapper.optimize(2)
    assert trained == [0, 1]
    mapper.optimize(6)
    assert set(trained[2:]) <= {0, 1} and len(trained) == 8
    assert mapper.keyframes[1].kind is KeyframeKind.MAPPING_ONLY


def test_map_growth_and_pruning_keep_optimizer_state_consistent(rasterizer, truth_frames):
    gm = start_map()
    mapper = make_mapper(rasterizer, gm, prune_every=0, max_scale=0.5)
    add(mapper, truth_frames[0])
    mapper.optimize(5)
    adam_consistent(mapper)
    # the core appends a keyframe's Gaussians between two optimize calls
    means, quats, scales, colors, _ = plane_scene(seed=5, n=40)
    rows = gm.append(means, quats, scales, colors, 0.1, np.ones(40, bool), 1)
    add(mapper, truth_frames[1], rows=rows)
    before_new = gm.colors[rows].clone()
    mapper.optimize(4)
    adam_consistent(mapper)
    assert torch.equal(mapper._adam.steps[rows], torch.full((40,), 4.0))  # own step count
    assert torch.equal(mapper._adam.steps[:N], torch.full((N,), 9.0))
    assert not torch.equal(gm.colors[rows], before_new)  # the new rows are trained
    # pruning: 5 transparent and 5 oversized Gaussians go, the moments of the others stay
    with torch.no_grad():
        gm.opacity_logits[:5] = math.log(0.001 / 0.999)
        gm.log_scales[5:10, 1] = math.log(0.8)
    kept_means = gm.means.detach()[10:].clone()
    m_colors = mapper._adam.m["colors"][10:].clone()
    assert mapper.prune() == 10
    assert len(gm) == N + 40 - 10
    torch.testing.assert_close(gm.means.detach(), kept_means, rtol=0, atol=0)
    torch.testing.assert_close(mapper._adam.m["colors"], m_colors, rtol=0, atol=0)
    adam_consistent(mapper)
    assert mapper.optimize(3) == 3 and np.isfinite(mapper.last_loss)


def test_rows_appended_during_a_step_are_kept_and_the_step_applies(rasterizer, truth_frames):
    """Real-time mode: the tracking thread appends a keyframe's Gaussians while a step renders
    (the lock is not held then). The step updates its own rows; the new rows stay as added."""
    gm = start_map()
    mapper = make_mapper(rasterizer, gm, prune_every=0)
    add(mapper, truth_frames[0])
    mapper.optimize(1)
    means, quats, scales, colors, _ = plane_scene(seed=6, n=30)
    appended = {}
    render = mapper.render

    def render_then_append(*args, **kwargs):
        out = render(*args, **kwargs)
        if not appended:
            appended["rows"] = gm.append(means, quats, scales, colors, 0.1, np.ones(30, bool), 1)
            appended["colors"] = gm.colors[appended["rows"]].clone()
        return out

    mapper.render = render_then_append
    before = gm.colors.detach()[:N].clone()
    assert mapper.optimize(1) == 1 and mapper.stale_steps == 0
    rows = appended["rows"]
    assert len(gm) == N + 30
    assert torch.equal(gm.colors.detach()[rows], appended["colors"])  # untouched
    assert not torch.equal(gm.colors.detach()[:N], before)  # the step's update reached the map
    mapper.render = render
    mapper.optimize(2)
    adam_consistent(mapper)


def test_a_step_is_dropped_when_rows_are_removed_during_it(rasterizer, truth_frames):
    gm = start_map()
    mapper = make_mapper(rasterizer, gm, prune_every=0)
    add(mapper, truth_frames[0])
    render = mapper.render

    def render_then_prune(*args, **kwargs):
        out = render(*args, **kwargs)
        with gm.lock:
            keep = torch.ones(len(gm), dtype=torch.bool)
            keep[:10] = False
            mapper._keep(keep)
        return out

    mapper.render = render_then_prune
    mapper.optimize(1)
    assert mapper.stale_steps == 1 and len(gm) == N - 10
    mapper.render = render
    assert mapper.optimize(2) == 2 and mapper.stale_steps == 1
    adam_consistent(mapper)


def test_periodic_pruning_uses_the_dataset_scale_limit(rasterizer, truth_frames):
    gm = start_map()
    with torch.no_grad():
        gm.log_scales[:7, 0] = math.log(0.3)  # above Replica's 0.25 m
    mapper = make_mapper(rasterizer, gm, prune_every=3, max_scale=0.25)
    add(mapper, truth_frames[0])
    mapper.optimize(3)
    assert len(gm) == N - 7
    adam_consistent(mapper)


def test_non_finite_loss_is_skipped(rasterizer, truth_frames, caplog):
    gm = start_map()
    mapper = make_mapper(rasterizer, gm)
    add(mapper, truth_frames[0])
    mapper.optimize(2)
    with torch.no_grad():
        gm.colors[7] = float("nan")  # a corrupt Gaussian in view: the loss is NaN
    good = torch.arange(len(gm)) != 7
    params = {k: v.detach()[good].clone() for k, v in gm.parameters().items()}
    moments = {k: v[good].clone() for k, v in mapper._adam.m.items()}
    steps = mapper._adam.steps[good].clone()
    with caplog.at_level(logging.WARNING):
        assert mapper.optimize(1) == 1  # attempted, skipped
    assert mapper.skipped_steps == 1 and "skipped" in caplog.text
    # the step changed nothing; the corrupt Gaussian is removed at once (with its moments)
    assert len(gm) == N - 1
    for k, v in gm.parameters().items():
        torch.testing.assert_close(v.detach(), params[k], rtol=0, atol=0, msg=k)
        torch.testing.assert_close(mapper._adam.m[k], moments[k], rtol=0, atol=0, msg=k)
    assert torch.equal(mapper._adam.steps, steps)
    adam_consistent(mapper)
    assert mapper.optimize(2) == 2 and mapper.skipped_steps == 1 and np.isfinite(mapper.last_loss)


def test_invalid_depth_values_are_masked(rasterizer, truth_frames):
    f = truth_frames[0]
    depth = f.depth.copy()
    depth[0, :5] = [np.nan, np.inf, -1.0, 0.0, -np.inf]
    mapper = make_mapper(rasterizer)
    add(mapper, Frame(0, 0.0, f.rgb, depth, f.camera, f.gt_pose))
    assert (mapper.keyframes[0].depth[0, :5] == 0).all()
    mapper.optimize(2)
    assert mapper.skipped_steps == 0 and np.isfinite(mapper.last_loss)


class GroundTruthTracker(Tracker):
    """Reports each frame's ground-truth pose with Gaussians from its depth; records the
    tracking target it is given at each tracking keyframe."""

    def __init__(self, stride: int = 3):
        self.stride = stride
        self.targets = []

    def track(self, frame, gaussian_map):
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
        self.targets.append(gaussian_map.tracking_target())


def test_tracking_keyframe_sees_the_optimised_map(rasterizer, truth_frames):
    """Through the SLAM loop: the target taken at the second tracking keyframe holds the values
    the mapper optimised, not the ones the first keyframe's Gaussians entered with."""
    tracker = GroundTruthTracker()
    mapper = GaussianSplattingMapper(GaussianSplattingConfig(resolution_scale=1.0, lr_means=1e-3),
                                     rasterizer=rasterizer, sampler=RandomSampler())
    gm = GaussianMap()
    slam = SLAM(tracker, EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=2)), mapper, gm,
                MapGrowthConfig(), iterations_per_frame=6)
    slam.initialize(np.eye(4))
    frames = [truth_frames[0], truth_frames[0], truth_frames[1]]
    snapshots = []
    for i, f in enumerate(frames):
        frame = Frame(i, float(i), f.rgb, f.depth, f.camera, f.gt_pose)
        step = slam.step(frame)
        if i == 0:
            n0 = len(gm)
        assert step.mapping_iterations == 6
        snapshots.append((gm.means.detach().clone(), gm.covariances().clone()))
    assert len(tracker.targets) == 2
    first, second = tracker.targets
    entered = torch.as_tensor(first.means)
    optimised_means, optimised_cov = snapshots[1]  # after frames 0 and 1's mapping steps
    target_means = torch.as_tensor(second.means[:n0])
    assert not torch.allclose(target_means, entered, atol=1e-5)  # the mapper moved them
    torch.testing.assert_close(target_means, optimised_means[:n0], rtol=0, atol=0)
    torch.testing.assert_close(torch.as_tensor(second.covariances[:n0]), optimised_cov[:n0], rtol=1e-6, atol=1e-9)
    assert second.version > first.version


def test_skip_covered_drops_gaussians_where_the_map_already_is(rasterizer, truth_frames):
    means, quats, scales, colors, _ = plane_scene(opacity=0.99)
    gm = make_map(means, quats, scales * 2, colors, 0.99)  # an opaque wall
    mapper = make_mapper(rasterizer, gm, skip_covered=True)
    frame = truth_frames[0]
    rng = np.random.default_rng(3)
    on = np.c_[rng.uniform(-0.6, 0.6, (20, 2)), np.full(20, 2.0)]
    front = np.c_[rng.uniform(-0.6, 0.6, (10, 2)), np.full(10, 1.4)]
    new = np.r_[on, front].astype(np.float32)
    g = FrameGaussians(new, np.tile(np.eye(3) * 1e-4, (30, 1, 1)), np.full((30, 3), 0.5), new[:, 2], np.ones(30, bool))
    result = TrackingResult(np.eye(4), gaussians=g)
    # the hook the core may call before adding the Gaussians
    mask = mapper.select_new_gaussians(frame, result)
    assert mask.tolist() == [False] * 20 + [True] * 10
    # without the hook: the rows just added are removed on arrival
    mapper._filtered.clear()
    rows = gm.append(new, np.tile([1.0, 0, 0, 0], (30, 1)), np.full((30, 3), 0.01), g.colors, 0.1, np.ones(30, bool), 1)
    mapper.add_keyframe(frame, result, KeyframeKind.TRACKING, rows)
    assert len(gm) == N + 10
    torch.testing.assert_close(gm.means.detach()[N:], torch.as_tensor(front, dtype=torch.float32))
    mapper.optimize(2)
    adam_consistent(mapper)


def test_densify_and_opacity_reset_smoke(rasterizer, truth_frames):
    gm = start_map()
    mapper = make_mapper(rasterizer, gm, densify=True, densify_every=3, densify_grad_threshold=1e-9,
                         densify_scale_threshold=0.09, opacity_reset=True, opacity_reset_every=4)
    add(mapper, truth_frames[0])
    mapper.optimize(3)
    assert len(gm) > N  # cloned (small) and split (large) Gaussians
    adam_consistent(mapper)
    mapper.optimize(1)
    assert float(gm.opacities.detach().max()) <= 0.01 + 1e-6
    mapper.optimize(2)
    adam_consistent(mapper)
    assert all(torch.isfinite(p).all() for p in gm.parameters().values())


def test_evaluate_reports_train_and_test_views_and_writes_outputs(rasterizer, truth_frames, tmp_path):
    mapper = make_mapper(rasterizer, save_images=2)
    add(mapper, truth_frames[0])
    mapper.optimize(20)
    mapper.finish()
    poses = [f.gt_pose for f in truth_frames]
    m = mapper.evaluate(truth_frames, poses, tmp_path)
    for key in ("psnr", "ssim", "psnr_train", "ssim_train", "psnr_test", "ssim_test", "depth_l1_cm"):
        assert isinstance(m[key], float) and math.isfinite(m[key]), key
    assert m["eval_frames"] == 2 and m["eval_train_frames"] == 1
    assert m["psnr"] == pytest.approx((m["psnr_train"] + m["psnr_test"]) / 2)
    assert sorted(p.name for p in tmp_path.glob("render_*.png")) == ["render_0000.png", "render_0001.png"]
    assert len(load_ply(tmp_path / "map.ply")) == m["num_gaussians"] == len(mapper.gaussian_map)
    half = mapper.evaluate(truth_frames, poses, None)
    mapper.cfg.eval_resolution_scale = 0.5
    assert mapper.evaluate(truth_frames, poses, None)["eval_frames"] == 2
    assert half["psnr"] == pytest.approx(m["psnr"])


def test_cli_run_writes_rendering_metrics_images_and_map(tmp_path):
    """`mapper=gaussian_splatting` end to end on a tiny synthetic sequence."""
    import json

    from conftest import run_slamkit

    out = tmp_path / "run"
    proc = run_slamkit(
        "dataset=synthetic", "dataset.num_frames=6", "dataset.width=64", "dataset.height=48",
        "tracker=gicp", "keyframe=every_n", "keyframe.tracking_every=3", "mapper=gaussian_splatting",
        "mapper.final_iterations=4", "mapper.save_images=2", "iterations_per_frame=2", "progress=false",
        f"hydra.run.dir={out}", cwd=tmp_path, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "psnr_train", "psnr_test", "depth_l1_cm"):
        assert math.isfinite(metrics[key]), key
    assert metrics["mapping_steps"] == 6 * 2 + 4 and metrics["eval_train_frames"] == 2
    assert len(load_ply(out / "map.ply")) == metrics["num_gaussians"] > 0
    assert len(list(out.glob("render_*.png"))) == 2
