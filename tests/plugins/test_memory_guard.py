"""The memory cap the trainer applies whatever the strategy (`mapper.memory_cap.max_gaussians`)
and the 3DGS mapper's keyframe image storage (issue 9). Heap release in a process of its own,
and the command with the cap: tests/e2e/test_memory_guard_runs.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from slamkit.errors import ConfigError
from slamkit.map.growth import MapGrowthConfig
from slamkit.metrics import trajectory as evaluation
from slamkit.registry.discovery import create_rasterizer
from slamkit.run.build import build_run
from slamkit.run.slam import SLAM
from slamkit_plugins.mappers.gaussian_splatting.keyframes import KEYFRAME_DEPTH_STEP, KeyframeStorage
from slamkit_plugins.mappers.gaussian_splatting.memory_cap import MemoryCapConfig

from support.mapping_scenes import (
    N,
    add,
    make_map,
    make_mapper,
    plane_scene,
    render_frame,
    rows,
    start_map,
    state_follows_map,
)


@pytest.fixture(scope="module")
def rasterizer():
    return create_rasterizer("torch")


@pytest.fixture(scope="module")
def frame(rasterizer):
    return render_frame(rasterizer, make_map(*plane_scene()), np.eye(4))


def capped(cap: int, margin: float = 0.1) -> dict:
    """The mapper's settings of a memory cap of `cap` Gaussians."""
    return {"memory_cap": MemoryCapConfig(max_gaussians=cap, margin=margin)}


@pytest.mark.parametrize("field, value", [("max_gaussians", 0), ("max_gaussians", -5), ("margin", 1.0),
                                          ("margin", -0.1)])
def test_guard_settings_are_validated(field, value):
    with pytest.raises(ConfigError, match=f"mapper.memory_cap.{field}: expected") as err:
        MemoryCapConfig(**{field: value})
    assert "\n" not in str(err.value)


def test_guard_prunes_the_least_opaque_down_to_the_margin_and_spares_new_rows(rasterizer, frame):
    gm = start_map()
    with torch.no_grad():  # distinct opacities, shuffled over the rows
        gm.opacity_logits.copy_(torch.linspace(-4, 4, N)[torch.randperm(N, generator=torch.Generator().manual_seed(0))])
    mapper = make_mapper(gm, strategy=("gsicp", {"prune_every": 0}), mapper=capped(320, 0.2))
    add(mapper, frame)
    mapper.optimize(3)
    assert len(gm) == N and mapper.memory_cap.prunings == 0  # within the cap
    # a keyframe adds 40 Gaussians: 340 > 320, so the guard prunes down to 0.8 x 320 = 256
    before = gm.opacities.detach().clone()
    new = gm.append(rows(*plane_scene(seed=5, n=40)[:4], 0.1, keyframe_id=1))
    new_means = gm.means.detach()[new].clone()
    version = gm.version
    add(mapper, frame, new_rows=new)
    assert len(gm) == 256 and gm.version > version
    assert mapper.memory_cap.metrics() == {"pruned_by_memory_cap": 84, "memory_cap_prunings": 1}
    torch.testing.assert_close(gm.means.detach()[-40:], new_means, rtol=0, atol=0)  # the new rows stay
    old = before[:N]
    kept = torch.sort(old, descending=True).values[:216]
    torch.testing.assert_close(torch.sort(gm.opacities.detach()[:216], descending=True).values, kept)
    assert mapper.optimize(2) == 2 and np.isfinite(mapper.last_loss)
    state_follows_map(mapper)
    assert mapper.evaluate([frame], [frame.gt_pose], None)["pruned_by_memory_cap"] == 84
    state = mapper.state_dict()  # a checkpoint before 0.4 names the counters as the memory guard's
    state["memory_cap"] = {"pruned_by_memory_guard": 84, "memory_guard_prunings": 1}
    mapper.memory_cap.pruned = mapper.memory_cap.prunings = 0
    mapper.load_state_dict(state)
    assert mapper.memory_cap.metrics() == {"pruned_by_memory_cap": 84, "memory_cap_prunings": 1}


def test_guard_prunes_new_rows_only_when_the_old_ones_cannot_make_room(rasterizer, frame):
    gm = start_map()
    mapper = make_mapper(gm, mapper=capped(50, 0.0))
    new = gm.append(rows(*plane_scene(seed=5, n=80)[:4], 0.1, keyframe_id=1))
    add(mapper, frame, new_rows=new)
    assert len(gm) == 50 and mapper.memory_cap.pruned == N + 30
    assert bool((gm.keyframe_id == 1).all())  # every old row went first
    mapper.optimize(1)
    state_follows_map(mapper)


def test_densification_respects_the_cap(rasterizer, frame):
    gm = start_map()
    mapper = make_mapper(gm, strategy=("3dgs", {"densify_every": 3, "grad_threshold": 1e-9}),
                         mapper=capped(N + 10, 0.0))
    add(mapper, frame)
    mapper.optimize(3)
    assert len(gm) <= N + 10 and mapper.memory_cap.prunings >= 1
    state_follows_map(mapper)


@pytest.mark.parametrize("storage", ["memory", "disk"])
def test_keyframe_images_are_quantised_and_stored(rasterizer, frame, storage, tmp_path):
    folder = tmp_path / "kf"
    mapper = make_mapper(mapper={"keyframe_storage": KeyframeStorage(storage), "keyframe_dir": str(folder)})
    add(mapper, frame)
    view = mapper.keyframes[0].view()
    image, depth = view.image, view.depth
    assert image.dtype == depth.dtype == torch.float32 and image.shape == (30, 40, 3)
    torch.testing.assert_close(image, torch.as_tensor(frame.rgb) / 255.0, rtol=0, atol=1e-6)
    valid = frame.depth > 0
    assert torch.equal(depth > 0, torch.as_tensor(valid))
    err = (depth - torch.as_tensor(frame.depth)).abs().max()
    assert float(err) <= KEYFRAME_DEPTH_STEP / 2 + 1e-6
    on_disk = sorted(p.name for p in folder.glob("*.npy")) if folder.exists() else []
    if storage == "disk":
        assert on_disk == ["keyframe_000000_depth.npy", "keyframe_000000_rgb.npy"]
        assert mapper.keyframes.memory_bytes() == 0
    else:
        assert on_disk == [] and mapper.keyframes.memory_bytes() == 30 * 40 * (3 + 2)
    mapper.optimize(3)
    assert np.isfinite(mapper.last_loss)


def test_disk_storage_trains_exactly_as_memory_storage(rasterizer, frame):
    losses = {}
    for storage in KeyframeStorage:
        mapper = make_mapper(mapper={"keyframe_storage": storage})
        add(mapper, frame)
        mapper.optimize(4)
        losses[storage] = (mapper.last_loss, mapper.gaussian_map.colors.detach().clone())
        if storage is KeyframeStorage.disk:
            folder = mapper.keyframes.folder
            assert folder.is_dir()
            del mapper
            import gc

            gc.collect()
            assert not folder.exists()  # a temporary folder goes with the mapper
    (a, ca), (b, cb) = losses.values()
    assert a == b
    torch.testing.assert_close(ca, cb, rtol=0, atol=0)


class RecordingTracker:
    """Wraps a tracker; at each target rebuild records the map's version and trackable count
    and the version of the target the tracker took."""

    def __init__(self, tracker):
        self._tracker = tracker
        self.rebuilds = []

    def __getattr__(self, name):
        return getattr(self._tracker, name)

    def update_target(self, gaussian_map):
        self._tracker.update_target(gaussian_map)
        with gaussian_map.lock:
            eligible = gaussian_map.trackable & (gaussian_map.opacities.detach() > self._tracker.min_opacity)
            self.rebuilds.append((gaussian_map.version, self._tracker.target.version,
                                  len(self._tracker.target.means), int(eligible.sum())))


@pytest.mark.slow
def test_guarded_replica_run_stays_under_the_cap_keeps_the_most_opaque_and_tracks(replica_path):
    """Replica room0, 8 frames, a keyframe every 2nd frame (each adds ~8k Gaussians), the map
    capped at 12,000: after every step the map is within the cap; each guard pruning removed
    Gaussians no more opaque than the lowest one kept among the older rows; the optimiser state
    follows; the tracker's target is rebuilt from the pruned map at the next tracking keyframe;
    tracking stays within the tracking-only bound."""
    cap = 12_000
    dataset, slam, _ = build_run(["dataset=replica", f"dataset.path={replica_path}", "dataset.max_frames=8",
                                  "tracker=gicp", "keyframe=every_n", "keyframe.tracking_every=2",
                                  "mapper=gaussian_splatting", "mapper.resolution_scale=0.25", "final_iterations=0",
                                  "mapper.eval_resolution_scale=0.25", "mapper.save_images=0",
                                  f"mapper.memory_cap.max_gaussians={cap}", "mapper.memory_cap.margin=0.1",
                                  "mapper.admission.skip_covered=false",  # every keyframe adds its ~8k Gaussians
                                  "iterations_per_frame=2"])
    gm, mapper = slam.gaussian_map, slam.mapper
    recorder = slam.tracker = RecordingTracker(slam.tracker)

    prunings, kept_masks = [], []
    guard, remove = mapper.memory_cap.enforce, mapper.edit.remove

    def guard_spy(edit, protect=None):
        logits, version, n, first = gm.opacity_logits.detach().clone(), gm.version, len(gm), len(kept_masks)
        removed = guard(edit, protect)
        if removed:
            prunings.append((logits, protect, n, removed, kept_masks[first], version, gm.version))
        return removed

    def remove_spy(drop):
        kept_masks.append(~drop.clone())
        return remove(drop)

    mapper.memory_cap.enforce, mapper.edit.remove = guard_spy, remove_spy

    slam.initialize(dataset[0].gt_pose)
    poses, gts = [], []
    for i in range(len(dataset)):
        frame = dataset[i]
        step = slam.process(frame)
        poses.append(step.tracking.pose)
        gts.append(frame.gt_pose)
        assert len(gm) <= cap, f"frame {i}: {len(gm)} Gaussians"
        state_follows_map(mapper)
        assert not step.tracking.lost

    assert len(prunings) >= 2 and mapper.memory_cap.pruned == sum(p[3] for p in prunings)
    for logits, protect, n, removed, mask, v_before, v_after in prunings:
        assert len(mask) == n and int((~mask).sum()) == removed
        old = torch.ones(n, dtype=torch.bool)
        old[protect] = False
        assert bool(mask[protect].all())  # the new keyframe's rows are spared
        assert removed == n - int(cap * 0.9)
        assert float(logits[old & mask].min()) >= float(logits[~mask].max())  # the most opaque stay
        assert v_after > v_before
    # each tracking keyframe rebuilds the target from the current (pruned) map
    assert len(recorder.rebuilds) == 4
    for map_version, target_version, target_size, eligible in recorder.rebuilds:
        assert target_version == map_version and target_size == eligible
    assert recorder.rebuilds[-1][0] > prunings[0][6]
    ate = evaluation.ate(np.array(poses), gts)
    assert ate.rmse_m < 0.01
    metrics = mapper.evaluate(dataset, poses, None)
    assert metrics["pruned_by_memory_cap"] == mapper.memory_cap.pruned > 0
    assert metrics["num_gaussians"] == len(gm) <= cap and math.isfinite(metrics["psnr"])
    assert metrics["keyframe_memory_mb"] > 0


def test_slam_releases_free_memory_at_each_keyframe(monkeypatch, rasterizer):
    import slamkit.run.slam
    from slamkit_plugins.keyframes.every_n import EveryNKeyframeConfig, EveryNKeyframePolicy

    from support.mapping_scenes import GroundTruthTracker

    calls = []
    monkeypatch.setattr(slamkit.run.slam, "release_free_memory", lambda: calls.append(1) or True)
    mapper = make_mapper(mapper=capped(100))
    slam = SLAM(GroundTruthTracker(), EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=2)), mapper,
                mapper.gaussian_map, MapGrowthConfig(), iterations_per_frame=1)
    frame = render_frame(rasterizer, start_map(), np.eye(4))
    slam.initialize(np.eye(4))
    for i in range(5):
        slam.process(frame.__class__(i, float(i), frame.rgb, frame.depth, frame.camera, frame.gt_pose))
        assert len(slam.gaussian_map) <= 100
    assert slam.num_keyframes == 3 and len(calls) == 3
