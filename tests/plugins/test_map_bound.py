"""A map bounded by the scene (issue 20, point 4): the coverage tests a keyframe's new Gaussians
go through (`slamkit_plugins.mappers.gaussian_splatting.coverage`, `mapper.admission.skip_covered`). A looped real
sequence whose map stops growing after the first pass: tests/e2e/test_map_bound_runs.py."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from slamkit.config import RunContext
from slamkit.errors import ConfigError
from slamkit.geometry.transforms import invert_pose
from slamkit.map.gaussian_map import GaussianMap
from slamkit.map.growth import MapGrowthConfig
from slamkit.registry.discovery import create_rasterizer
from slamkit.roles import Tracker
from slamkit.roles.rendering import RenderOutput
from slamkit.run.slam import SLAM
from slamkit.tuning import DatasetTuning
from slamkit.types import FrameGaussians, TrackingResult
from slamkit_plugins.keyframes.every_n import EveryNKeyframeConfig, EveryNKeyframePolicy
from slamkit_plugins.mappers.gaussian_splatting.admission import AdmissionConfig, CoverageTest
from slamkit_plugins.mappers.gaussian_splatting.coverage import DepthTolerance, covered_by_render, occupied_by_centres

from support.mapping_scenes import CAM, N, make_mapper, plane_scene, render_frame
from support.mapping_scenes import make_map as make_scene_map


def make_map(means, quats, scales, colors, opacity):
    """The scene's map as no keyframe of the SLAM under test added it (keyframe id -1): the keyframe
    grown next is that SLAM's keyframe 0, whose rows already in the map (in real time, its trackable
    ones) the admission leaves out of its coverage."""
    return make_scene_map(means, quats, scales, colors, opacity, keyframe_id=-1)


def at_pixel(u: float, v: float, z: float, pose: np.ndarray = np.eye(4)) -> np.ndarray:
    """The world point (metres) seen at pixel (u, v) at camera depth z by CAM at `pose`
    (camera-to-world)."""
    camera_point = np.array([(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z, 1.0])
    return (pose @ camera_point)[:3]


def occupied(points, centres, pose=np.eye(4), cell=5.0, tolerance=0.05, min_centres=1, quadratic=0.0) -> list[bool]:
    w2c = torch.as_tensor(invert_pose(pose), dtype=torch.float32)
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32).reshape(-1, 3))  # noqa: E731
    return occupied_by_centres(t(points), t(centres), w2c, CAM, cell, DepthTolerance(tolerance, quadratic),
                               min_centres).tolist()


@pytest.mark.parametrize("pose", [np.eye(4),
                                  np.array([[0.0, 0, 1, 0.3], [0, 1, 0, -0.2], [-1, 0, 0, 1.5], [0, 0, 0, 1]])])
def test_a_point_is_occupied_by_a_centre_near_its_pixel_at_its_depth(pose):
    """Cell 5 px: a disc of radius 3.54 px (CAM: 40x30); depth tolerance 5 cm, the two combined as
    an ellipse (pixel distance / radius)^2 + (depth difference / tolerance)^2 < 1; any camera pose."""
    centres = [at_pixel(12.0, 7.0, 2.0, pose), at_pixel(31.0, 22.0, 2.0, pose), at_pixel(29.0, 19.0, 3.0, pose)]
    points = [
        at_pixel(13.0, 8.0, 2.03, pose),  # 1.4 px from the first centre, 3 cm behind: 0.16 + 0.36
        at_pixel(12.4, 7.4, 1.96, pose),  # 0.6 px, 4 cm in front: 0.03 + 0.64
        at_pixel(12.0, 7.0, 2.2, pose),  # same pixel, 20 cm behind: a different surface
        at_pixel(15.0, 7.0, 2.0, pose),  # 3 px to the right, same depth: within the disc
        at_pixel(16.0, 7.0, 2.0, pose),  # 4 px: outside it
        at_pixel(14.0, 9.0, 2.04, pose),  # 2.8 px and 4 cm: each within reach, together not (0.64 + 0.64)
        at_pixel(30.0, 21.0, 2.98, pose),  # the centre at 3 m explains it
        at_pixel(30.0, 21.0, 2.5, pose),  # between the two centres: neither within 5 cm
        at_pixel(-3.0, 7.0, 2.0, pose),  # outside the image
    ]
    behind = (pose @ np.array([0.0, 0.0, -2.0, 1.0]))[:3]  # behind the camera, on its axis
    assert occupied(points + [behind], centres, pose) == [True, True, False, True, False, False, True, False, False,
                                                          False]
    assert occupied(points, [], pose) == [False] * len(points)
    # a larger cell takes in the point 4 px away; a larger tolerance the surface 20 cm behind
    assert occupied(points[4], centres, pose, cell=10.0) == [True]
    assert occupied(points[2], centres, pose, tolerance=0.25) == [True]
    # two centres needed: only where two lie within reach
    two = centres + [at_pixel(11.0, 6.0, 1.98, pose)]  # a second centre near the first
    assert occupied(points[:2] + points[6:8], two, pose, min_centres=2) == [False, True, False, False]
    assert occupied(points[6:8], two, pose, tolerance=0.8, min_centres=2) == [False, True]  # 2.5 m: both in reach
    assert occupied(points[:2], two, pose, min_centres=3) == [False, False]


def test_the_depth_tolerance_grows_with_the_square_of_the_depth():
    """max(5 cm, 0.01 z^2): 5 cm up to 2.24 m, 16 cm at 4 m; both tests take it."""
    tolerance = DepthTolerance(0.05, 0.01)
    z = torch.tensor([0.5, 1.0, 2.0, 3.0, 4.0, 8.0], dtype=torch.float64)
    assert torch.allclose(tolerance.at(z), torch.tensor([0.05, 0.05, 0.05, 0.09, 0.16, 0.64], dtype=torch.float64))
    assert torch.equal(DepthTolerance(0.05).at(z), torch.full_like(z, 0.05))
    # the depth coordinate's slope is 1 / tolerance, continuous where the quadratic takes over
    fine = torch.linspace(0.3, 9.0, 20001, dtype=torch.float64)
    slope = torch.diff(tolerance.coordinate(fine)) / torch.diff(fine)
    assert torch.allclose(slope, 1.0 / tolerance.at((fine[1:] + fine[:-1]) / 2), rtol=1e-3)
    far = [at_pixel(20.0, 15.0, 4.0)]
    assert occupied(far, [at_pixel(20.0, 15.0, 4.12)], quadratic=0.01) == [True]  # 12 cm < 16 cm at 4 m
    assert occupied(far, [at_pixel(20.0, 15.0, 4.12)]) == [False]
    assert occupied(far, [at_pixel(20.0, 15.0, 4.2)], quadratic=0.01) == [False]
    # the render test: an opaque render at 4.12 m explains a point at 4 m only with the quadratic term
    render = RenderOutput(torch.zeros(CAM.height, CAM.width, 3), torch.full((CAM.height, CAM.width), 4.12),
                          torch.ones(CAM.height, CAM.width))
    point = torch.as_tensor(np.array(far, dtype=np.float32))
    assert covered_by_render(point, render, torch.eye(4), CAM, 0.9, tolerance).tolist() == [True]
    assert covered_by_render(point, render, torch.eye(4), CAM, 0.9, DepthTolerance(0.05)).tolist() == [False]


@pytest.mark.parametrize("angle", [0.0, 0.2, 0.45, 0.785])
def test_a_grid_of_centres_a_cell_apart_occupies_a_view_at_any_rotation(angle):
    """A wall sampled every 5 px by one keyframe, seen by another rotated about its optical
    axis: every sample of the second view inside the first's footprint is occupied (the square
    cells of earlier versions left some of them empty at angles other than 0)."""
    us, vs = np.meshgrid(np.arange(-40.0, 80.0, 5.0), np.arange(-40.0, 70.0, 5.0))
    first = np.array([at_pixel(u, v, 2.0) for u, v in zip(us.ravel(), vs.ravel())])
    c, s = np.cos(angle), np.sin(angle)
    rotated = np.eye(4)
    rotated[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]  # about the optical axis
    samples = [at_pixel(u, v, 2.0, rotated) for u in np.arange(0.0, 40.0, 5.0) for v in np.arange(0.0, 30.0, 5.0)]
    assert all(occupied(samples, first, rotated))


def test_coverage_settings_are_validated_and_the_cell_comes_from_the_dataset_tuning():
    with pytest.raises(ConfigError, match="mapper.admission.covered_cell: expected null or > 0 pixels"):
        AdmissionConfig(covered_cell=0)
    with pytest.raises(ConfigError, match="mapper.admission.covered_centres: expected an integer >= 1"):
        AdmissionConfig(covered_centres=0)
    with pytest.raises(ConfigError, match="mapper.admission.covered_depth_quadratic: expected >= 0 per metre"):
        AdmissionConfig(covered_depth_quadratic=-0.01)
    with pytest.raises(ConfigError, match="mapper.admission.coverage"):
        from slamkit.run.build import build_run

        build_run(["dataset=synthetic", "mapper=gaussian_splatting", "mapper.admission.coverage=nearby"])
    cfg = AdmissionConfig().resolve(RunContext(tuning=DatasetTuning(tracking_pixel_stride=10)))
    assert cfg.covered_cell == 10  # the sampling stride
    assert AdmissionConfig(covered_cell=3).resolve(RunContext()).covered_cell == 3


class PlaneTracker(Tracker):
    """Ground-truth poses; its keyframe Gaussians: 20 on the map's wall at z = 2 m and 10
    floating in front (z = 1.4 m), all overlapping the tracking target (not trackable), and 5 on
    the wall that are new surface for tracking (trackable)."""

    def track(self, frame):
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


def grow_once(gm, **admission) -> tuple[int, object]:
    """One keyframe of PlaneTracker's Gaussians into `gm` through SLAM; (Gaussians added, mapper).
    Cell 5 px: the 300 map Gaussians leave no sample of CAM without a centre near it."""
    if "coverage" in admission:
        admission["coverage"] = CoverageTest(admission["coverage"])
    mapper = make_mapper(gm, mapper={"admission": AdmissionConfig(**{"covered_cell": 5.0, **admission})})
    slam = SLAM(PlaneTracker(), EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=1)), mapper, gm,
                MapGrowthConfig(new_gaussian_overlap=1e-3), iterations_per_frame=0)
    slam.initialize(np.eye(4))
    frame = render_frame(create_rasterizer("torch"), make_map(*plane_scene()), np.eye(4))
    before, structure = len(gm), gm.structure_version
    slam.process(frame)
    assert gm.structure_version == structure  # decided before appending: nothing added and removed
    return len(gm) - before, mapper


def test_more_centres_a_cell_admit_more_of_a_keyframe():
    """mapper.admission.covered_centres=8 (the map's 300 centres put about 5-10 in a point's disc of 3.5
    px): discs with fewer no longer count as explained, so more of the keyframe enters."""
    one, _ = grow_once(make_map(*plane_scene()))
    eight, _ = grow_once(make_map(*plane_scene()), covered_centres=8)
    assert eight > one


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
    assert mapper.admission.skipped == 20


@pytest.mark.parametrize("coverage", ["centres", "render"])
def test_the_strategy_takes_the_quadratic_depth_tolerance(coverage):
    """mapper.admission.covered_depth_quadratic=0.35: 69 cm at 1.4 m, so the wall at 2 m explains the
    floating points 60 cm in front of it, and only the trackable ones enter."""
    means, quats, scales, colors, _ = plane_scene()
    added, _ = grow_once(make_map(means, quats, scales * 2, colors, 0.99), coverage=coverage,
                         covered_depth_quadratic=0.35)
    assert added == 5


def test_without_skip_covered_every_keyframe_gaussian_enters():
    gm = make_map(*plane_scene(opacity=0.99))
    added, mapper = grow_once(gm, skip_covered=False)
    assert added == 35 and mapper.admission.skipped == 0


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

    def track(self, frame):
        rng = np.random.default_rng(4)
        means = np.c_[rng.uniform(-0.6, 0.6, (40, 2)), np.full(40, 3.0)].astype(np.float32)
        g = FrameGaussians(means, np.tile(np.eye(3) * 1e-4, (40, 1, 1)), np.full((40, 3), 0.5), means[:, 2],
                           np.ones(40, bool), sq_dist_to_map=np.full(40, np.inf))
        return TrackingResult(frame.gt_pose, gaussians=g)


def test_gaussians_the_target_lacks_yet_are_not_made_trackable_twice():
    """The tracker measures new surface against its target, which only a tracking keyframe
    rebuilds. A keyframe whose Gaussians duplicate a mapping-only keyframe's (added since the
    target was built) must not make them trackable again: trackable Gaussians enter the map
    whatever the coverage test says, so a loop would add them at every revisit (with mapping-only
    keyframes' Gaussians trackable, `growth.mapping_only_trackable=true`)."""
    gm = GaussianMap()
    mapper = make_mapper(gm, mapper={"admission": AdmissionConfig(covered_cell=5.0)})
    slam = SLAM(TargetlessTracker(), EveryNKeyframePolicy(EveryNKeyframeConfig(tracking_every=3, mapping_every=1)),
                mapper, gm, MapGrowthConfig(new_gaussian_overlap=1e-3, mapping_only_trackable=True),
                iterations_per_frame=0)
    slam.initialize(np.eye(4))
    frame = render_frame(create_rasterizer("torch"), make_map(*plane_scene()), np.eye(4))
    kinds, sizes = [], []
    for i in range(5):
        kinds.append(slam.process(dataclasses.replace(frame, index=i)).keyframe.value)
        sizes.append(len(gm))
    assert kinds == ["tracking", "mapping_only", "mapping_only", "tracking", "mapping_only"]
    # frame 1: the target lacks nothing yet (frame 0's rows are in it), so all 40 are new
    # surface and enter; frames 2 and 3: frame 1's 40 rows are not in the target yet and are
    # duplicated exactly: not trackable, covered, left out; frame 3, a tracking keyframe,
    # rebuilds the target from the map, so at frame 4 it lacks nothing again
    assert sizes == [40, 80, 80, 80, 120]
    assert int(gm.trackable.sum()) == 120
    assert mapper.admission.skipped == 80
