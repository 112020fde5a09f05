"""A map bounded by the scene (issue 20, point 4): the coverage tests a keyframe's new Gaussians
go through (`slamkit.map.coverage`, `strategy.skip_covered`), and a looped real sequence whose
map stops growing after the first pass."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest
import torch

from mapping_scenes import CAM, N, make_map, make_mapper, plane_scene, render_frame
from slamkit.errors import ConfigError
from slamkit.geometry.transforms import invert_pose
from slamkit.map.coverage import image_cells, occupied_by_centres
from slamkit.map.gaussian_map import GaussianMap
from slamkit.map.growth import MapGrowthConfig
from slamkit.registry.discovery import create_rasterizer
from slamkit.roles import SensorProfile, Tracker
from slamkit.run.slam import SLAM
from slamkit.types import FrameGaussians, TrackingResult
from slamkit_plugins.keyframes.every_n import EveryNKeyframeConfig, EveryNKeyframePolicy
from slamkit_plugins.strategies.gsicp import PruneConfig


def at_pixel(u: float, v: float, z: float, pose: np.ndarray = np.eye(4)) -> np.ndarray:
    """The world point (metres) seen at pixel (u, v) at camera depth z by CAM at `pose`
    (camera-to-world)."""
    camera_point = np.array([(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z, 1.0])
    return (pose @ camera_point)[:3]


def occupied(points, centres, pose=np.eye(4), cell=5.0, tolerance=0.05, min_centres=1) -> list[bool]:
    w2c = torch.as_tensor(invert_pose(pose), dtype=torch.float32)
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32).reshape(-1, 3))  # noqa: E731
    return occupied_by_centres(t(points), t(centres), w2c, CAM, cell, tolerance, min_centres).tolist()


@pytest.mark.parametrize("pose", [np.eye(4), np.array([[0.0, 0, 1, 0.3], [0, 1, 0, -0.2], [-1, 0, 0, 1.5], [0, 0, 0, 1]])])
def test_a_point_is_occupied_by_a_centre_in_its_cell_at_its_depth(pose):
    """Cells of 5x5 pixels centred on every 5th pixel (CAM: 40x30); depth tolerance 5 cm; any
    camera pose."""
    centres = [at_pixel(12.0, 7.0, 2.0, pose),  # cell (column 2, row 1): pixels [7.5, 12.5) x [2.5, 7.5)
               at_pixel(31.0, 22.0, 2.0, pose), at_pixel(29.0, 19.0, 3.0, pose)]  # cell (6, 4) at two depths
    points = [
        at_pixel(8.0, 3.0, 2.03, pose),  # same cell as the first centre, 3 cm behind it: occupied
        at_pixel(12.4, 7.4, 1.96, pose),  # same cell, 4 cm in front: occupied
        at_pixel(12.0, 7.0, 2.2, pose),  # same pixel, 20 cm behind: a different surface
        at_pixel(13.0, 7.0, 2.0, pose),  # the next cell to the right: empty
        at_pixel(30.0, 21.0, 2.98, pose),  # cell (6, 4): the centre at 3 m explains it
        at_pixel(30.0, 21.0, 2.5, pose),  # cell (6, 4), between the two: neither within 5 cm
        at_pixel(-3.0, 7.0, 2.0, pose),  # outside the image
    ]
    behind = (pose @ np.array([0.0, 0.0, -2.0, 1.0]))[:3]  # behind the camera, on its axis
    assert occupied(points + [behind], centres, pose) == [True, True, False, False, True, False, False, False]
    assert occupied(points, [], pose) == [False] * len(points)
    # a larger cell takes in the neighbour; a larger tolerance the surface 20 cm behind
    assert occupied(points[3], centres, pose, cell=10.0) == [True]
    assert occupied(points[2], centres, pose, tolerance=0.25) == [True]
    # two centres needed: only where two lie in the cell within the tolerance
    two = centres + [at_pixel(8.0, 6.0, 1.99, pose)]  # a second centre in the first cell
    assert occupied(points[:2] + points[4:6], two, pose, min_centres=2) == [True, True, False, False]
    assert occupied(points[4:6], two, pose, tolerance=0.6, min_centres=2) == [False, True]  # 2.5 m: both in reach
    assert occupied(points[:2], two, pose, min_centres=3) == [False, False]


def test_image_cells_number_the_image_row_by_row():
    points = torch.as_tensor(np.array([at_pixel(0.0, 0.0, 1.0), at_pixel(39.4, 0.0, 1.0), at_pixel(0.0, 29.4, 1.0),
                                       at_pixel(40.0, 0.0, 1.0)], dtype=np.float32))
    cell, z, inside = image_cells(points, torch.eye(4), CAM, 10.0)
    columns = 6  # cells centred on columns 0, 10, 20, 30, 40 (and a spare)
    assert inside.tolist() == [True, True, True, False]
    assert cell[:3].tolist() == [0, 4, 3 * columns]
    assert torch.allclose(z, torch.ones(4, dtype=torch.float64))


def test_coverage_settings_are_validated_and_the_cell_comes_from_the_sensor():
    with pytest.raises(ConfigError, match="strategy.covered_cell: expected null or > 0 pixels"):
        PruneConfig(covered_cell=0)
    with pytest.raises(ConfigError, match="strategy.covered_centres: expected an integer >= 1"):
        PruneConfig(covered_centres=0)
    with pytest.raises(ConfigError, match="strategy.coverage"):
        from slamkit.registry.compose import build_run

        build_run(["dataset=synthetic", "mapper=gaussian_splatting", "strategy.coverage=nearby"])
    cfg = PruneConfig().with_sensor(SensorProfile(tracking_pixel_stride=10, max_gaussian_scale=0.25))
    assert cfg.covered_cell == 10 and cfg.max_scale == 0.25  # the sampling stride
    assert PruneConfig(covered_cell=3).with_sensor(SensorProfile()).covered_cell == 3


class PlaneTracker(Tracker):
    """Ground-truth poses; its keyframe Gaussians: 20 on the map's wall at z = 2 m and 10
    floating in front (z = 1.4 m), all overlapping the tracking target (not trackable), and 5 on
    the wall that are new surface for tracking (trackable)."""

    def track(self, frame, gaussian_map):
        rng = np.random.default_rng(3)
        on = np.c_[rng.uniform(-0.6, 0.6, (20, 2)), np.full(20, 2.0)]
        front = np.c_[rng.uniform(-0.6, 0.6, (10, 2)), np.full(10, 1.4)]
        trackable = np.c_[rng.uniform(-0.6, 0.6, (5, 2)), np.full(5, 2.0)]
        new = np.r_[on, front, trackable].astype(np.float32)
        n = len(new)
        sq_dist = np.r_[np.zeros(30), np.full(5, np.inf)]
        g = FrameGaussians(new, np.tile(np.eye(3) * 1e-4, (n, 1, 1)), np.full((n, 3), 0.5), new[:, 2],
                           np.ones(n, bool), sq_dist_to_map=sq_dist)
        return TrackingResult(frame.gt_pose, gaussians=g)


def grow_once(gm, **strategy) -> tuple[int, object]:
    """One keyframe of PlaneTracker's Gaussians into `gm` through SLAM; (Gaussians added, mapper).
    Cells of 5x5 pixels: the 300 map Gaussians leave none of CAM's cells empty."""
    mapper = make_mapper(gm, strategy=("gsicp", {"covered_cell": 5.0, **strategy}))
    slam = SLAM(PlaneTracker(), EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=1)), mapper, gm,
                MapGrowthConfig(new_gaussian_overlap=1e-3), iterations_per_frame=0)
    slam.initialize(np.eye(4))
    frame = render_frame(create_rasterizer("torch"), make_map(*plane_scene()), np.eye(4))
    before, structure = len(gm), gm.structure_version
    slam.step(frame)
    assert gm.structure_version == structure  # decided before appending: nothing added and removed
    return len(gm) - before, mapper


def test_more_centres_a_cell_admit_more_of_a_keyframe():
    """strategy.covered_centres=2 (the map's 300 centres hold one or two per 5x5 cell): cells
    with a single centre no longer count as explained, so more of the keyframe enters."""
    one, _ = grow_once(make_map(*plane_scene()))
    two, _ = grow_once(make_map(*plane_scene()), covered_centres=2)
    assert two > one


@pytest.mark.parametrize("coverage", ["centres", "render", "either"])
def test_skip_covered_admits_the_uncovered_and_the_trackable(coverage):
    """An opaque wall at z = 2 m: every test finds the wall explained and the floating points
    not; trackable points enter whatever the test says."""
    means, quats, scales, colors, _ = plane_scene()
    gm = make_map(means, quats, scales * 2, colors, 0.99)
    added, mapper = grow_once(gm, coverage=coverage)
    assert added == 15
    new = gm.means.detach()[N:]
    assert int((new[:, 2] < 1.5).sum()) == 10  # the floating ones
    assert int(gm.trackable[N:].sum()) == 5
    assert mapper.strategy.metrics()["skipped_as_covered"] == 20


def test_without_skip_covered_every_keyframe_gaussian_enters():
    gm = make_map(*plane_scene(opacity=0.99))
    added, mapper = grow_once(gm, skip_covered=False)
    assert added == 35 and mapper.strategy.metrics()["skipped_as_covered"] == 0


def test_centres_explain_an_untrained_map_where_the_render_does_not():
    """Gaussians as they enter the map (opacity 0.1, untrained, as in real-time mode before the
    mapper reached them): the render is too faint to cover anything, so the render test admits
    the wall again; the centres test does not."""
    means, quats, scales, colors, _ = plane_scene()
    added_render, _ = grow_once(make_map(means, quats, scales, colors, 0.1), coverage="render")
    added_centres, _ = grow_once(make_map(means, quats, scales, colors, 0.1), coverage="centres")
    assert added_render == 35
    assert added_centres == 15


class TargetlessTracker(Tracker):
    """Ground-truth poses; every frame the same 40 Gaussians on a wall at z = 3 m, all reported
    far from the tracker's target (it never builds one): new surface for tracking every time."""

    def track(self, frame, gaussian_map):
        rng = np.random.default_rng(4)
        means = np.c_[rng.uniform(-0.6, 0.6, (40, 2)), np.full(40, 3.0)].astype(np.float32)
        g = FrameGaussians(means, np.tile(np.eye(3) * 1e-4, (40, 1, 1)), np.full((40, 3), 0.5), means[:, 2],
                           np.ones(40, bool), sq_dist_to_map=np.full(40, np.inf))
        return TrackingResult(frame.gt_pose, gaussians=g)


def test_gaussians_the_target_lacks_yet_are_not_made_trackable_twice():
    """The tracker measures new surface against its target, which only a tracking keyframe
    rebuilds. A keyframe whose Gaussians duplicate a mapping-only keyframe's (added since the
    target was built) must not make them trackable again: trackable Gaussians enter the map
    whatever the coverage test says, so a loop would add them at every revisit."""
    gm = GaussianMap()
    mapper = make_mapper(gm, strategy=("gsicp", {"covered_cell": 5.0}))
    slam = SLAM(TargetlessTracker(), EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=3, mapping_every=1)),
                mapper, gm, MapGrowthConfig(new_gaussian_overlap=1e-3), iterations_per_frame=0)
    slam.initialize(np.eye(4))
    frame = render_frame(create_rasterizer("torch"), make_map(*plane_scene()), np.eye(4))
    kinds, sizes = [], []
    for i in range(5):
        kinds.append(slam.step(dataclasses.replace(frame, index=i)).keyframe.value)
        sizes.append(len(gm))
    assert kinds == ["tracking", "mapping_only", "mapping_only", "tracking", "mapping_only"]
    # frame 1: the target lacks nothing yet (frame 0's rows are in it), so all 40 are new
    # surface and enter; frames 2 and 3: frame 1's 40 rows are not in the target yet and are
    # duplicated exactly: not trackable, covered, left out; frame 3, a tracking keyframe,
    # rebuilds the target from the map, so at frame 4 it lacks nothing again
    assert sizes == [40, 80, 80, 80, 120]
    assert int(gm.trackable.sum()) == 120
    assert mapper.strategy.metrics()["skipped_as_covered"] == 80


# -- end to end: a looped real sequence ---------------------------------------------------------

LOOP = ["dataset=tum", "dataset.start=120", "dataset.stride=3", "dataset.passes=3",  # 10 frames a pass
        "keyframe=every_n", "keyframe.tracking_every=2", "final_iterations=0", "progress=false", "eval.plot=false"]
MAPPING = ["mapper=gaussian_splatting", "mapper.resolution_scale=0.25", "mapper.eval_resolution_scale=0.25",
           "mapper.eval_every=5", "mapper.save_images=0"]


def loop_run(tmp_path, tum_path, name: str, *overrides: str) -> tuple[list[int], dict]:
    """Gaussians after each frame (frames.csv) and metrics.json of a looped TUM run."""
    from conftest import run_slamkit

    out = tmp_path / name
    proc = run_slamkit(*LOOP, f"dataset.path={tum_path}", *overrides, f"hydra.run.dir={out}", cwd=tmp_path,
                       env_extra={"OMP_NUM_THREADS": "1"}, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    sizes = [int(r["num_gaussians"]) for r in csv.DictReader(open(out / "frames.csv"))]
    return sizes, json.loads((out / "metrics.json").read_text())


def growth_by_pass(sizes: list[int], frames_per_pass: int = 10) -> tuple[int, int]:
    """(Gaussians the first pass added, Gaussians the later passes added)."""
    first = sizes[frames_per_pass - 1]
    return first, sizes[-1] - first


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["sequential", "realtime"])
def test_a_looped_sequence_stops_growing_the_map_after_the_first_pass(tmp_path, tum_path, mode):
    """TUM fr1/rpy frames 120-147 every 3rd, played forth, back and forth (28 frames), a keyframe
    every 2nd frame, training at a quarter resolution: with the default growth the passes after
    the first add at most 10% of what the first added; with every keyframe's Gaussians admitted
    (skip_covered off) they add at least half as much again. Tracking is the same."""
    run_mode = ["mode=realtime", "fps_limit=30"] if mode == "realtime" else ["iterations_per_frame=2"]
    bounded, m_bounded = loop_run(tmp_path, tum_path, "bounded", *MAPPING, *run_mode)
    unbounded, m_unbounded = loop_run(tmp_path, tum_path, "unbounded", *MAPPING, "strategy.skip_covered=false",
                                      *run_mode)
    assert len(bounded) == len(unbounded) == 28
    first, later = growth_by_pass(bounded)
    assert first > 5000 and later <= 0.1 * first, (first, later)
    first_all, later_all = growth_by_pass(unbounded)
    assert later_all >= 0.5 * first_all, (first_all, later_all)
    assert m_bounded["skipped_as_covered"] > 0 and m_unbounded["skipped_as_covered"] == 0
    assert m_bounded["ate_rmse_m"] < 0.05 and m_unbounded["ate_rmse_m"] < 0.05


@pytest.mark.slow
def test_tracking_only_a_looped_sequence_stops_growing_the_map_after_the_first_pass(tmp_path, tum_path):
    """mapper=none admits only new surface for tracking: the same loop adds at most 10% after
    the first pass."""
    sizes, metrics = loop_run(tmp_path, tum_path, "tracking", "mapper=none")
    first, later = growth_by_pass(sizes)
    assert first > 1000 and later <= 0.1 * first, (first, later)
    assert metrics["ate_rmse_m"] < 0.05


@pytest.mark.slow
def test_a_looped_sequence_with_mapping_only_keyframes_stops_growing(tmp_path, replica_path):
    """Replica room0's 20 frames played back and forth 9 times, tracking only, the default
    keyframes: after four tracking keyframes the target covers the room and every keyframe is
    mapping-only (every 10th frame), revisiting a few views. Each view's new surface enters
    once; the last two passes (frames 134-171) add under 2 % of what the first pass added
    (measuring new surface against the tracker's target alone, each revisit added ~5,600)."""
    from conftest import run_slamkit

    out = tmp_path / "replica"
    proc = run_slamkit("dataset=replica", f"dataset.path={replica_path}", "dataset.passes=9", "mapper=none",
                       "progress=false", "eval.plot=false", f"hydra.run.dir={out}", cwd=tmp_path,
                       env_extra={"OMP_NUM_THREADS": "1"}, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    frames = list(csv.DictReader(open(out / "frames.csv")))
    sizes = [int(r["num_gaussians"]) for r in frames]
    assert len(sizes) == 172
    assert sum(r["keyframe"] == "mapping_only" for r in frames[134:]) >= 3
    first, last_two = sizes[19], sizes[-1] - sizes[133]
    assert first > 30000 and last_two <= 0.02 * first, (first, last_two)
