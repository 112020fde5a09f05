"""The 3DGS mapper (`mapper=gaussian_splatting`) as a trainer composed of parts: keyframes,
the training loop, its thread safety, evaluation. The parts have their own test files
(test_strategies, test_optimizers, test_samplers, test_losses, core/test_map_editing); the command
with it: tests/e2e/test_mapper_runs.py."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from PIL import Image

from slamkit.errors import ConfigError
from slamkit.formats.ply import load_ply
from slamkit.map.gaussian_map import GaussianMap
from slamkit.map.growth import MapGrowthConfig
from slamkit.registry.discovery import create_rasterizer
from slamkit.run.build import build_run
from slamkit.run.slam import SLAM
from slamkit.types import Camera, Frame, KeyframeKind
from slamkit_plugins.keyframes.every_n import EveryNKeyframeConfig, EveryNKeyframePolicy
from slamkit_plugins.mappers.gaussian_splatting import GaussianSplattingConfig
from slamkit_plugins.mappers.gaussian_splatting.keyframes import resize_rgbd
from slamkit_plugins.mappers.gaussian_splatting.sampler.keyframe_samplers import CovisibleSampler

from support.mapping_scenes import (
    GroundTruthTracker,
    N,
    add,
    make_map,
    make_mapper,
    plane_scene,
    pose_x,
    render_frame,
    rows,
    start_map,
    state_follows_map,
)


@pytest.fixture(scope="module")
def rasterizer():
    return create_rasterizer("torch")


@pytest.fixture(scope="module")
def truth_frames(rasterizer):
    truth = make_map(*plane_scene())
    return [render_frame(rasterizer, truth, pose_x(x), i) for i, x in enumerate((0.0, 0.15))]


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


def test_the_mapper_is_composed_of_the_parts_the_config_names(replica_path):
    _, slam, _ = build_run(["dataset=replica", f"dataset.path={replica_path}", "mapper=gaussian_splatting",
                            "mapper/rasterizer=torch", "mapper/sampler=covisible", "mapper.sampler.top_k=2",
                            "mapper/strategy=3dgs", "mapper.strategy.densify_every=50", "mapper/optimizer=visible_adam",
                            "mapper.optimizer.lr_colors=0.01", "mapper.loss.weight_ssim=0.3"])
    mapper = slam.mapper
    assert isinstance(mapper.sampler, CovisibleSampler) and mapper.sampler.cfg.top_k == 2
    assert type(mapper.rasterizer).__name__ == "TorchRasterizer"
    assert mapper.strategy.cfg.densify_every == 50
    assert mapper.strategy.cfg.max_scale == 0.25  # null: Replica's sensor profile
    assert mapper.optimizer.cfg.lr_colors == 0.01 and mapper.loss.cfg.weight_ssim == 0.3
    with pytest.raises(ConfigError, match="sampler"):
        build_run(["mapper=gaussian_splatting", "mapper/sampler=nope"])
    with pytest.raises(ConfigError, match="mapper.resolution_scale"):
        GaussianSplattingConfig(resolution_scale=0)


@pytest.mark.parametrize("overrides, size", [([], (240, 320)), (["mode=realtime"], (120, 160)),
                                             (["mode=realtime", "mapper.resolution_scale=0.5"], (240, 320))])
def test_training_resolution_left_null_depends_on_the_mode(tum_path, overrides, size):
    """Null: half the frame's size in sequential mode, a quarter in real time; a value set wins
    (the keyframes a checkpoint keeps are at the training resolution)."""
    dataset, slam, _ = build_run(["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=1",
                                  "mapper=gaussian_splatting", *overrides])
    slam.initialize(dataset[0].gt_pose)
    slam.process(dataset[0])
    slam.settle()  # real time: the keyframe goes to the mapper beside tracking
    assert slam.mapper.state_dict()["keyframes"]["rgb"].shape[1:3] == size


def test_a_resumed_mapper_trains_new_keyframes_at_its_checkpoints_resolution(tum_path):
    """A real-time run's keyframes (a quarter of the frame size) resumed in sequential mode (whose
    default is half): the next keyframe is stored at a quarter too, not mixed."""
    common = ["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=2", "mapper=gaussian_splatting",
              "keyframe=every_n", "keyframe.tracking_every=1"]
    dataset, slam, _ = build_run([*common, "mode=realtime"])
    slam.initialize(dataset[0].gt_pose)
    slam.process(dataset[0])
    slam.settle()  # real time: the keyframe goes to the mapper beside tracking
    state = slam.mapper.state_dict()
    dataset, resumed, _ = build_run(common)
    resumed.initialize(dataset[0].gt_pose)
    resumed.mapper.load_state_dict(state)
    resumed.process(dataset[1])
    rgb = resumed.mapper.state_dict()["keyframes"]["rgb"]
    assert rgb.shape[0] == 2 and rgb.shape[1:3] == (120, 160)

@pytest.mark.parametrize("optimizer", ["adam", "visible_adam"])
@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_training_one_view_lowers_loss_and_raises_psnr(truth_frames, backend, optimizer):
    frame = truth_frames[0]
    mapper = make_mapper(rasterizer=backend, optimizer=optimizer)
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
    state_follows_map(mapper)


def test_new_keyframe_trained_first_then_sampled(truth_frames):
    mapper = make_mapper()
    trained = []
    step = mapper.step
    mapper.step = lambda view: trained.append(view.keyframe_id) or step(view)
    add(mapper, truth_frames[0])
    add(mapper, truth_frames[1], KeyframeKind.MAPPING_ONLY)
    assert mapper.optimize(0) == 0
    mapper.optimize(2)
    assert trained == [0, 1]
    mapper.optimize(6)
    assert set(trained[2:]) <= {0, 1} and len(trained) == 8
    assert mapper.keyframes[1].kind is KeyframeKind.MAPPING_ONLY


def test_training_views_are_kept_between_steps_within_their_budget(truth_frames):
    mapper = make_mapper()  # 40x30 views: 19 kB each
    add(mapper, truth_frames[0])
    add(mapper, truth_frames[1])
    store = mapper.keyframes
    first = store.view(0)
    assert torch.equal(first.image, store[0].view().image) and torch.equal(first.depth, store[0].view().depth)
    assert store.view(0).image is first.image and store.view(0, scale=0.5).image is not first.image
    one_view = (first.image.nbytes + first.depth.nbytes) / 2**20
    small = make_mapper(mapper={"view_cache_mb": 1.5 * one_view})
    off = make_mapper(mapper={"view_cache_mb": 0})
    for m in (small, off):
        add(m, truth_frames[0])
        add(m, truth_frames[1])
    kept = small.keyframes.view(0)
    assert small.keyframes.view(0).image is kept.image
    small.keyframes.view(1)  # the budget holds one: keyframe 0's is dropped
    assert small.keyframes.view(0).image is not kept.image
    assert off.keyframes.view(0).image is not off.keyframes.view(0).image


def test_the_least_recently_used_view_is_dropped_first(truth_frames):
    probe = make_mapper()
    add(probe, truth_frames[0])
    one_view = (probe.keyframes.view(0).image.nbytes + probe.keyframes.view(0).depth.nbytes) / 2**20
    mapper = make_mapper(mapper={"view_cache_mb": 2.5 * one_view})
    for frame in (*truth_frames, truth_frames[0]):  # three keyframes
        add(mapper, frame)
    views = mapper.keyframes
    first, second = views.view(0), views.view(1)
    views.view(0)  # used again: keyframe 1's is now the least recently used
    views.view(2)
    assert views.view(0).image is first.image and views.view(1).image is not second.image


def test_a_negative_view_cache_size_is_a_clear_error():
    with pytest.raises(ConfigError, match="view_cache_mb"):
        make_mapper(mapper={"view_cache_mb": -1})


def test_kept_views_train_as_fresh_ones(truth_frames):
    maps = []
    for cache_mb in (64.0, 0.0):
        mapper = make_mapper(mapper={"view_cache_mb": cache_mb})
        add(mapper, truth_frames[0])
        add(mapper, truth_frames[1])
        mapper.optimize(8)
        maps.append(mapper.gaussian_map.parameters())
    for name in maps[0]:
        assert torch.equal(maps[0][name], maps[1][name]), name


def test_coarse_steps_train_a_new_keyframe_at_half_resolution_first(truth_frames):
    mapper = make_mapper(mapper={"coarse_steps": 3})
    widths = []
    step = mapper.step
    mapper.step = lambda view: widths.append(view.camera.width) or step(view)
    add(mapper, truth_frames[0])
    mapper.optimize(5)
    assert widths == [20, 20, 20, 40, 40] and np.isfinite(mapper.last_loss)


def test_a_window_step_trains_on_the_same_pixels_of_its_view(truth_frames):
    """mapper.window=0.5: each step takes a random window of the 40x30 view (20x16 pixels: at
    least 16 a side, clipped where it reaches out of the view), whose camera renders that part of
    the view's render; the map still learns the view."""
    mapper = make_mapper(mapper={"window": 0.5})
    windows = []
    step = mapper.step
    mapper.step = lambda view: windows.append(view) or step(view)
    add(mapper, truth_frames[0])
    mapper.optimize(1)
    first = mapper.last_loss
    mapper.optimize(60)
    assert mapper.last_loss < 0.6 * first
    full = mapper.keyframes[0].view()
    assert {(w.camera.height, w.camera.fx) for w in windows} == {(16, full.camera.fx)}
    assert {w.camera.width for w in windows} <= set(range(16, 21)) and len({w.camera.width for w in windows}) > 1
    with torch.no_grad():
        whole = mapper.render(full.world_to_camera, full.camera)
        corners = set()
        for w in windows[-8:]:
            x0, y0 = round(full.camera.cx - w.camera.cx), round(full.camera.cy - w.camera.cy)
            corners.add((x0, y0))
            rows, columns = slice(y0, y0 + w.camera.height), slice(x0, x0 + w.camera.width)
            assert torch.equal(w.image, full.image[rows, columns]) and torch.equal(w.depth, full.depth[rows, columns])
            part = mapper.render(w.world_to_camera, w.camera)
            # the same pixels, but near the window's border: 3DGS clamps the projection's Jacobian
            # at 15 % outside the image, so Gaussians beyond the window's edge spread differently
            inner = (slice(4, -4), slice(4, -4))
            assert torch.allclose(part.color[inner], whole.color[rows, columns][inner], atol=1e-5)
            assert torch.allclose(part.depth[inner], whole.depth[rows, columns][inner], atol=1e-5)
            assert torch.allclose(part.color, whole.color[rows, columns], atol=5e-3)
    assert len(corners) > 1
    with pytest.raises(ValueError, match="not inside the 40x30 view"):
        full.window(30, 0, 20, 15)


def test_a_small_window_keeps_the_loss_s_minimum_size():
    """A window of a quarter of a 20x15 coarse view would be 5x4 pixels, below SSIM's 11x11:
    it takes 16 pixels (or the whole side) instead, and training runs."""
    mapper = make_mapper(mapper={"window": 0.25, "coarse_steps": 2})
    sizes = []
    step = mapper.step
    mapper.step = lambda view: sizes.append((view.camera.width, view.camera.height)) or step(view)
    frame = render_frame(create_rasterizer("torch"), start_map(), pose_x(0.0))
    add(mapper, frame)
    assert mapper.optimize(4) == 4 and np.isfinite(mapper.last_loss)
    assert all(w >= 16 and h == 15 for w, h in sizes[:2]) and all(w >= 16 and h >= 16 for w, h in sizes[2:])
    with pytest.raises(ConfigError, match="mapper.window: expected in \\(0, 1\\]"):
        GaussianSplattingConfig(window=0.0)


def test_rows_appended_between_steps_get_trained(truth_frames):
    gm = start_map()
    mapper = make_mapper(gm, strategy=("gsicp", {"prune_every": 0}))
    add(mapper, truth_frames[0])
    mapper.optimize(5)
    new = gm.append(rows(*plane_scene(seed=5, n=40), keyframe_id=1))  # the core adds a keyframe's Gaussians
    add(mapper, truth_frames[1], new_rows=new)
    before = gm.colors.detach()[new].clone()
    mapper.optimize(4)
    state_follows_map(mapper)
    assert not torch.equal(gm.colors.detach()[new], before)


def test_rows_appended_during_a_step_are_kept_and_the_step_applies(truth_frames):
    """Real-time mode: the tracking thread appends a keyframe's Gaussians while a step renders
    (the lock is not held then). The step updates its own rows; the new rows stay as added."""
    gm = start_map()
    mapper = make_mapper(gm, strategy=("gsicp", {"prune_every": 0}))
    add(mapper, truth_frames[0])
    mapper.optimize(1)
    appended = {}
    render = mapper.render

    def render_then_append(*args, **kwargs):
        out = render(*args, **kwargs)
        if not appended:
            appended["rows"] = gm.append(rows(*plane_scene(seed=6, n=30), keyframe_id=1))
            appended["colors"] = gm.colors.detach()[appended["rows"]].clone()
        return out

    mapper.render = render_then_append
    before = gm.colors.detach()[:N].clone()
    assert mapper.optimize(1) == 1 and mapper.stale_steps == 0
    assert len(gm) == N + 30
    assert torch.equal(gm.colors.detach()[appended["rows"]], appended["colors"])  # untouched
    assert not torch.equal(gm.colors.detach()[:N], before)  # the step's update reached the map
    mapper.render = render
    mapper.optimize(2)
    state_follows_map(mapper)


def test_a_step_is_dropped_when_rows_are_removed_during_it(truth_frames):
    gm = start_map()
    mapper = make_mapper(gm, strategy=("gsicp", {"prune_every": 0}))
    add(mapper, truth_frames[0])
    render = mapper.render

    def render_then_remove(*args, **kwargs):
        out = render(*args, **kwargs)
        with gm.lock:
            drop = torch.zeros(len(gm), dtype=torch.bool)
            drop[:10] = True
            mapper.edit.remove(drop)
        return out

    mapper.render = render_then_remove
    mapper.optimize(1)
    assert mapper.stale_steps == 1 and len(gm) == N - 10
    mapper.render = render
    assert mapper.optimize(2) == 2 and mapper.stale_steps == 1
    state_follows_map(mapper)


def test_non_finite_loss_is_skipped_and_the_corrupt_gaussian_removed(truth_frames, caplog):
    gm = start_map()
    mapper = make_mapper(gm, optimizer="visible_adam")
    add(mapper, truth_frames[0])
    mapper.optimize(2)
    with torch.no_grad():
        gm.colors[7] = float("nan")  # a corrupt Gaussian in view: the loss is NaN
    good = torch.arange(len(gm)) != 7
    params = {k: v.detach()[good].clone() for k, v in gm.parameters().items()}
    state = {k: [t[good] for t in v] for k, v in mapper.optimizer.row_state().items()}
    with caplog.at_level(logging.WARNING):
        assert mapper.optimize(1) == 1  # attempted, skipped
    assert mapper.skipped_steps == 1 and "skipped" in caplog.text
    # the step changed nothing; the corrupt Gaussian is removed at once (with its state)
    assert len(gm) == N - 1
    for k, v in gm.parameters().items():
        torch.testing.assert_close(v.detach(), params[k], rtol=0, atol=0, msg=k)
    for k, tensors in mapper.optimizer.row_state().items():
        for t, expected in zip(tensors, state[k]):
            torch.testing.assert_close(t, expected, rtol=0, atol=0, msg=k)
    state_follows_map(mapper)
    assert mapper.optimize(2) == 2 and mapper.skipped_steps == 1 and np.isfinite(mapper.last_loss)


def test_invalid_depth_values_are_masked(truth_frames):
    f = truth_frames[0]
    depth = f.depth.copy()
    depth[0, :5] = [np.nan, np.inf, -1.0, 0.0, -np.inf]
    mapper = make_mapper()
    add(mapper, Frame(0, 0.0, f.rgb, depth, f.camera, f.gt_pose))
    assert (mapper.keyframes[0].view().depth[0, :5] == 0).all()
    mapper.optimize(2)
    assert mapper.skipped_steps == 0 and np.isfinite(mapper.last_loss)


@pytest.mark.parametrize("geometry", ["optimised", "entry"])
def test_a_tracking_keyframe_takes_the_target_geometry_it_asks_for(truth_frames, geometry):
    """Through the SLAM loop: the target taken at the second tracking keyframe holds the values
    the mapper optimised ("optimised", the reference code's exchange), or the ones the first
    keyframe's Gaussians entered with ("entry", G-ICP's default) while the mapper moved them."""
    tracker = GroundTruthTracker(geometry=geometry)
    gm = GaussianMap()
    mapper = make_mapper(gm, optimizer=("adam", {"lr_means": 1e-3}))
    slam = SLAM(tracker, EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=2)), mapper, gm,
                MapGrowthConfig(), iterations_per_frame=6)
    slam.initialize(np.eye(4))
    frames = [truth_frames[0], truth_frames[0], truth_frames[1]]
    snapshots = []
    for i, f in enumerate(frames):
        step = slam.process(Frame(i, float(i), f.rgb, f.depth, f.camera, f.gt_pose))
        if i == 0:
            n0 = len(gm)
        assert step.mapping_iterations == 6
        snapshots.append((gm.means.detach().clone(), gm.covariances().clone()))
    assert len(tracker.targets) == 2
    first, second = tracker.targets
    entered = torch.as_tensor(first.means)
    optimised_means, optimised_cov = snapshots[1]  # after frames 0 and 1's mapping steps
    target_means = torch.as_tensor(second.means[:n0])
    assert not torch.allclose(optimised_means[:n0], entered, atol=1e-5)  # the mapper moved them
    if geometry == "optimised":
        torch.testing.assert_close(target_means, optimised_means[:n0], rtol=0, atol=0)
        torch.testing.assert_close(torch.as_tensor(second.covariances[:n0]), optimised_cov[:n0], rtol=1e-6,
                                   atol=1e-9)
    else:
        torch.testing.assert_close(target_means, entered, rtol=0, atol=0)
        torch.testing.assert_close(torch.as_tensor(second.covariances[:n0]), torch.as_tensor(first.covariances),
                                   rtol=0, atol=0)
    assert second.version > first.version


def test_evaluate_reports_train_and_test_views_and_writes_outputs(truth_frames, tmp_path):
    mapper = make_mapper(mapper={"save_images": 2})
    add(mapper, truth_frames[0])
    mapper.optimize(20)
    mapper.finish()
    poses = [f.gt_pose for f in truth_frames]
    m = mapper.evaluate(truth_frames, poses, tmp_path)
    for key in ("psnr", "ssim", "psnr_train", "ssim_train", "psnr_test", "ssim_test", "depth_l1_cm"):
        assert isinstance(m[key], float) and math.isfinite(m[key]), key
    assert m["eval_frames"] == 2 and m["eval_train_frames"] == 1 and m["mapping_steps"] == 20
    assert m["psnr"] == pytest.approx((m["psnr_train"] + m["psnr_test"]) / 2)
    assert sorted(p.name for p in tmp_path.glob("render_*.png")) == ["render_0000.png", "render_0001.png"]
    # render | input | depth error under a label strip; the input panel is the frame itself
    panels = np.asarray(Image.open(tmp_path / "render_0000.png").convert("RGB"))
    h, w = truth_frames[0].rgb.shape[:2]
    assert panels.shape == (h + 14, 3 * w, 3) and panels[:14].any()  # the labels are drawn
    np.testing.assert_allclose(panels[14:, w:2 * w].astype(int), truth_frames[0].rgb.astype(int), atol=1)
    assert not (tmp_path / "map.ply").exists()  # the run writes the map before evaluating (save_map)
    assert mapper.save_map(tmp_path) == [tmp_path / "map.ply"]
    assert len(load_ply(tmp_path / "map.ply")) == m["num_gaussians"] == len(mapper.gaussian_map)
    half = make_mapper(mapper.gaussian_map, mapper={"eval_resolution_scale": 0.5})
    assert half.evaluate(truth_frames, poses, None)["eval_frames"] == 2


def test_the_mappers_built_in_parts_sit_in_the_folder_of_their_config_group():
    """The folder tree reads like the config tree: a built-in plugin of the part `mapper/<key>`
    is a module of `slamkit_plugins.mappers.gaussian_splatting.<key>`, and the mapper is its
    trainer (a subclass, not an object it forwards to)."""
    from slamkit.registry.discovery import default_registry
    from slamkit.roles import PARTS, Mapper
    from slamkit_plugins.mappers.gaussian_splatting import GaussianSplattingMapper
    from slamkit_plugins.mappers.gaussian_splatting.trainer import Trainer

    registry = default_registry()
    for part in PARTS:
        modules = {r.spec.cls.__module__ for r in registry.plugins[part.key].values()}
        built_in = {m for m in modules if m.startswith("slamkit_plugins.")}
        assert built_in, part.key
        assert all(m.startswith(f"slamkit_plugins.mappers.gaussian_splatting.{part.key}.") for m in built_in), built_in
    assert issubclass(GaussianSplattingMapper, Trainer) and issubclass(Trainer, Mapper)
