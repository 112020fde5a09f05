"""The built-in synthetic dataset: shapes, determinism, geometric consistency, cache, config."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.geometry.transforms import backproject, invert_pose, rotation_angle_deg, transform_points
from slamkit_plugins.datasets import synthetic
from slamkit_plugins.datasets.synthetic import SyntheticConfig, SyntheticDataset, sensor

SMALL = dict(num_frames=8, width=96, height=72)


@pytest.fixture(scope="module")
def default_ds(tmp_path_factory):
    """The default sequence (120 frames, 320x240), generated once into a private cache."""
    return SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path_factory.mktemp("synthetic_cache")), depth_noise=0.0))


def test_default_frames_and_shapes(default_ds):
    ds = default_ds
    assert len(ds) == ds.num_available() == 120
    cam = ds.camera
    assert (cam.width, cam.height) == (320, 240)
    assert cam.fx == cam.fy and 250 < cam.fx < 262
    assert (cam.cx, cam.cy) == (159.5, 119.5)
    assert ds.depth_trunc == 6.0
    for i in (0, 59, 119):
        f = ds[i]
        assert f.index == i and f.timestamp == pytest.approx(i / 30.0)
        assert f.rgb.shape == (240, 320, 3) and f.rgb.dtype == np.uint8
        assert f.depth.shape == (240, 320) and f.depth.dtype == np.float32
        assert f.gt_pose.shape == (4, 4) and f.gt_pose.dtype == np.float64
        R = f.gt_pose[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # Exact depth: no holes, everything inside the room.
        assert f.depth.min() > 0.3 and f.depth.max() < 8.0


def test_motion_is_hand_held_like(default_ds):
    poses = np.stack([default_ds[i].gt_pose for i in range(len(default_ds))])
    speed = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * 30
    rel = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    ang = rotation_angle_deg(rel) * 30
    assert 0.05 < speed.mean() < 0.6 and speed.max() < 1.0
    assert ang.max() < 45.0
    assert np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3]) > 0.1


@pytest.mark.parametrize("seed", [0, 1, 2, 7])
def test_camera_keeps_clear_of_surfaces(seed):
    poses = synthetic.handheld_path(900, seed)
    lo, hi = synthetic.PATH_BOUNDS
    assert np.all(poses[:, :3, 3] >= lo) and np.all(poses[:, :3, 3] <= hi)
    assert synthetic.scene_clearance(poses[:, :3, 3]).min() >= 0.5


def test_free_zone_is_clear():
    lo, hi = synthetic.PATH_BOUNDS
    grid = np.stack(np.meshgrid(*[np.linspace(lo[k], hi[k], 9) for k in range(3)], indexing="ij"), -1).reshape(-1, 3)
    assert synthetic.scene_clearance(grid).min() >= 0.5


def test_depth_consistent_with_ground_truth(default_ds):
    """Frame i's depth, moved with the GT poses into frame i + 5, matches frame i + 5's depth."""
    for i in (0, 40, 80, 110):
        fi, fj = default_ds[i], default_ds[i + 5]
        pts, _ = backproject(fi.depth, fi.camera)
        pj = transform_points(invert_pose(fj.gt_pose) @ fi.gt_pose, pts.astype(np.float64))
        c = fj.camera
        z = pj[:, 2]
        u = c.fx * pj[:, 0] / z + c.cx
        v = c.fy * pj[:, 1] / z + c.cy
        inside = (z > 0) & (u >= 0) & (u < c.width - 1) & (v >= 0) & (v < c.height - 1)
        assert inside.mean() > 0.5
        u, v, z = u[inside], v[inside], z[inside]
        u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
        a, b = u - u0, v - v0
        D = fj.depth.astype(np.float64)
        z_obs = (D[v0, u0] * (1 - a) + D[v0, u0 + 1] * a) * (1 - b) + (
            D[v0 + 1, u0] * (1 - a) + D[v0 + 1, u0 + 1] * a
        ) * b
        err = np.abs(z - z_obs)
        assert np.median(err) < 1e-3, f"frames {i}->{i + 5}: median depth error {np.median(err) * 1000:.2f} mm"
        # Nearest-pixel lookup too (the brief's 5 mm bound).
        ui, vi = np.round(u).astype(int), np.round(v).astype(int)
        assert np.median(np.abs(z - D[vi, ui])) < 5e-3


def test_texture_variety(default_ds):
    for i in (0, 60, 119):
        rgb = default_ds[i].rgb
        assert rgb.reshape(-1, 3).std(axis=0).mean() > 25
        coarse = np.unique((rgb.reshape(-1, 3) // 64).astype(np.int32) @ np.array([16, 4, 1]))
        assert len(coarse) >= 8  # several distinct surfaces/colours
        # High-frequency detail: neighbouring pixels differ somewhere (texture, not flat fill).
        grad = np.abs(np.diff(rgb.astype(np.int16), axis=1)).sum(-1)
        assert (grad > 30).mean() > 0.01


def test_scene_primitives_distinct_materials():
    names = {p.name for p in synthetic.scene()}
    for expected in ("floor", "ceiling", "sofa seat", "table top", "cabinet", "shelf side", "beach ball", "lamp pole"):
        assert expected in names


def test_deterministic_same_seed(tmp_path):
    a = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path / "a"), seed=3, **SMALL))
    b = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path / "b"), seed=3, **SMALL))
    for i in range(len(a)):
        fa, fb = a[i], b[i]
        np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_array_equal(fa.depth, fb.depth)
        np.testing.assert_array_equal(fa.gt_pose, fb.gt_pose)


def test_different_seed_different_path(tmp_path):
    a = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path), seed=0, **SMALL))
    b = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path), seed=1, **SMALL))
    assert a.cache_path != b.cache_path
    pa = np.stack([a[i].gt_pose for i in range(len(a))])
    pb = np.stack([b[i].gt_pose for i in range(len(b))])
    assert np.abs(pa - pb).max() > 0.1
    assert not np.array_equal(a[0].rgb, b[0].rgb)


def test_cache_is_reused(tmp_path, monkeypatch):
    cfg = SyntheticConfig(cache_dir=str(tmp_path), **SMALL)
    first = SyntheticDataset(cfg)
    assert first.cache_path.is_file() and first.cache_path.parent == tmp_path
    assert not list(tmp_path.glob("*.tmp"))  # written atomically, no leftovers
    frames = [first[i] for i in range(len(first))]

    def no_render(*args, **kwargs):
        raise AssertionError("the cached sequence was rendered again")

    monkeypatch.setattr(synthetic.dataset, "render", no_render)  # where the dataset looks it up
    second = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path), **SMALL))
    for i, f in enumerate(frames):
        g = second[i]
        np.testing.assert_array_equal(f.rgb, g.rgb)
        np.testing.assert_array_equal(f.depth, g.depth)
        np.testing.assert_array_equal(f.gt_pose, g.gt_pose)
    # Options that do not change the generated frames share the cache file.
    third = SyntheticDataset(
        SyntheticConfig(cache_dir=str(tmp_path), max_frames=3, stride=2, depth_noise=0.01, **SMALL)
    )
    assert third.cache_path == first.cache_path and len(third) == 3


def test_corrupt_cache_is_regenerated(tmp_path):
    cfg = SyntheticConfig(cache_dir=str(tmp_path), **SMALL)
    ds = SyntheticDataset(cfg)
    ref = ds[2].depth
    ds.close()
    ds.cache_path.write_bytes(b"not a zip file")
    again = SyntheticDataset(cfg)
    np.testing.assert_array_equal(again[2].depth, ref)


def test_cache_dir_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path))
    ds = SyntheticDataset(SyntheticConfig(**SMALL))
    assert ds.cache_path.parent == tmp_path / "synthetic" and ds.cache_path.is_file()


def test_depth_noise_and_dropout(tmp_path):
    clean = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path), depth_noise=0.0, **SMALL))
    noisy = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path), depth_noise=0.005, depth_dropout=0.1, **SMALL))
    d0, d1 = clean[1].depth, noisy[1].depth
    assert np.all(d0 > 0)
    holes = d1 == 0
    assert 0.05 < holes.mean() < 0.15
    resid = (d1 - d0)[~holes] / d0[~holes] ** 2
    assert 0.003 < resid.std() < 0.007
    np.testing.assert_array_equal(noisy[1].depth, d1)  # deterministic


@pytest.mark.parametrize(
    "values",
    [
        dict(num_frames=0),
        dict(num_frames=1),
        dict(width=8),
        dict(height=4),
        dict(fov_deg=0.0),
        dict(seed=-1),
        dict(depth_noise=-0.1),
        dict(depth_dropout=1.0),
        dict(speed=0.0),
        dict(stride=0),
    ],
)
def test_invalid_config(values):
    with pytest.raises(ConfigError):
        SyntheticConfig(**values)


def test_hook_returns_the_plugin():
    (spec,) = synthetic.slamkit_plugins()
    assert spec.name == "synthetic" and spec.cls is SyntheticDataset and spec.config is SyntheticConfig


def test_entry_point_declared():
    from importlib.metadata import entry_points

    eps = {ep.name: ep.value for ep in entry_points(group="slamkit")}
    assert eps.get("synthetic") == "slamkit_plugins.datasets.synthetic"


def test_unwritable_cache_falls_back_to_memory(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    ds = SyntheticDataset(SyntheticConfig(cache_dir=str(blocker / "cache"), **SMALL))
    ref = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path / "ok"), **SMALL))
    np.testing.assert_array_equal(ds[4].rgb, ref[4].rgb)
    np.testing.assert_array_equal(ds[4].depth, ref[4].depth)


# -- paths that come back and the structured-light sensor (issue 46) ---------------------------------

LOOP_FRAMES = {"room_loop": 600, "figure_eight": 720, "return": 900, "revisit_rotated": 900}


@pytest.mark.parametrize("kind", synthetic.LOOP_PATHS)
def test_a_loop_path_stays_clear_moves_like_a_hand_and_comes_back(kind):
    """Each path keeps to the free zone, at hand-held speeds (under 1 m/s and 45 deg/s), travels
    metres, and its last frames look again at what its first frames saw: some frame of the last
    tenth has its place (centre + 2 m along its axis) within 0.5 m of a frame's of the first
    tenth and its axis within 45 degrees of that frame's."""
    poses = synthetic.loop_path(kind, LOOP_FRAMES[kind], seed=3)
    lo, hi = synthetic.PATH_BOUNDS
    assert np.all(poses[:, :3, 3] >= lo) and np.all(poses[:, :3, 3] <= hi)
    assert synthetic.scene_clearance(poses[:, :3, 3]).min() >= 0.5
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turn = rotation_angle_deg(np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3]))
    assert step.max() * synthetic.FPS < 1.0 and turn.max() * synthetic.FPS < 45.5
    assert step.sum() > 3.0
    places = poses[:, :3, 3] + 2.0 * poses[:, :3, 2]
    first, last = slice(0, len(poses) // 10), slice(int(0.9 * len(poses)), None)
    near = np.linalg.norm(places[last, None] - places[None, first], axis=2) < 0.5
    aligned = poses[last, :3, 2] @ poses[first, :3, 2].T > np.cos(np.radians(45.0))
    assert np.any(near & aligned)


def test_the_return_path_ends_at_its_first_pose_and_revisit_rotated_turns_its_second_lap():
    back = synthetic.loop_path("return", 300, seed=1)
    np.testing.assert_allclose(back[-1], back[0], atol=1e-9)
    rotated = synthetic.loop_path("revisit_rotated", 300, seed=1)
    # the same angle round the ellipse on the way out and back: 25 degrees apart in heading
    out, home = rotated[30], rotated[-31]
    assert 20.0 < rotation_angle_deg(out[:3, :3].T @ home[:3, :3]) < 30.0


@pytest.mark.parametrize("kind", synthetic.LOOP_PATHS)
def test_a_ramp_starts_a_path_from_rest_and_without_one_the_path_is_unchanged(kind):
    """`ramp_s`: the first frames move little (the hand's bob goes on) and speed up to the path's
    pace; 0 is the path of before to the bit (every committed figure was measured on it)."""
    n = LOOP_FRAMES[kind]
    moving, ramped = synthetic.loop_path(kind, n, seed=3), synthetic.loop_path(kind, n, seed=3, ramp_s=1.0)
    np.testing.assert_array_equal(synthetic.loop_path(kind, n, seed=3, ramp_s=0.0), moving)
    np.testing.assert_array_equal(ramped[0], moving[0])  # the same start pose
    np.testing.assert_allclose(ramped[-1], moving[-1], atol=1e-9 if kind != "return" else 1e-6)

    def steps(poses):
        return np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)

    start, pace = steps(ramped)[:3].mean(), np.median(steps(ramped))
    assert start < 0.25 * pace and steps(moving)[:3].mean() > 0.5 * np.median(steps(moving))
    ramp = steps(ramped)[: int(synthetic.FPS)]
    assert np.all(np.diff(ramp) > -0.1 * pace)  # speeds up, give or take the hand's bob


#: Camera positions (metres) at frames 0, n/3, 2n/3 and n-1 of each path (seed 3, LOOP_FRAMES), from
#: the paths every committed synthetic figure was measured on (before `ramp_s` existed).
MEASURED_ON = {
    "room_loop": [[-0.044681130092, 0.448750513198, 1.376969589199], [-0.402825849949, -0.333502437352, 1.392029271263],
                  [0.599825333172, 0.01085739139, 1.478978418791], [-0.418829424385, 0.322222479374, 1.502964399879]],
    "figure_eight": [[0.0, 0.0, 1.444441986009], [0.444598183278, -0.447827100207, 1.496440780346],
                     [-0.597102800275, 0.087911169494, 1.411764987255],
                     [0.352671151375, 0.427975432333, 1.440476159095]],
    "return": [[0.362436002779, 0.496748209722, 1.39348302428], [0.094699475193, -0.198137065787, 1.569744308739],
               [-0.247487287158, -0.238674940046, 1.630855004862], [0.362436002779, 0.496748209722, 1.39348302428]],
    "revisit_rotated": [[-0.044681130092, 0.448750513198, 1.376969589199],
                        [0.414913178882, 0.32505994504, 1.487652575016],
                        [0.209825510426, 0.160810310726, 1.502098938381],
                        [-0.022340565046, 0.224375256599, 1.414230405373]],
}


@pytest.mark.parametrize("kind", synthetic.LOOP_PATHS)
def test_without_a_ramp_a_path_is_the_one_the_figures_were_measured_on(kind):
    n = LOOP_FRAMES[kind]
    poses = synthetic.loop_path(kind, n, seed=3, ramp_s=0.0)
    np.testing.assert_allclose(poses[[0, n // 3, 2 * n // 3, n - 1], :3, 3], MEASURED_ON[kind], atol=1e-9)


def test_a_ramp_progress_is_a_trapezoid_of_speed():
    np.testing.assert_array_equal(synthetic.from_rest(5, ramp_s=0.0), np.linspace(0, 1, 5))  # no ramp: constant
    u = synthetic.from_rest(301, ramp_s=1.0)
    assert u[0] == 0.0 and u[-1] == pytest.approx(1.0)
    np.testing.assert_allclose(u + u[::-1], 1.0, atol=1e-12)  # symmetric: slows to rest at the end
    speed = np.diff(u)
    np.testing.assert_allclose(np.diff(speed[:30]), np.diff(speed[:30]).mean(), rtol=1e-6)  # even acceleration
    np.testing.assert_allclose(speed[40:260], speed[150], rtol=1e-9)  # then constant


def test_an_unknown_path_is_refused_in_one_line():
    with pytest.raises(ConfigError, match="dataset.camera_path"):
        SyntheticConfig(camera_path="spiral")
    with pytest.raises(ValueError, match="spiral"):
        synthetic.loop_path("spiral", 10)
    with pytest.raises(ConfigError, match="dataset.ramp_s"):
        SyntheticConfig(ramp_s=1.0)  # the hand-held wander has no ramp
    with pytest.raises(ConfigError, match="dataset.ramp_s"):
        SyntheticConfig(camera_path="return", ramp_s=-1.0)
    with pytest.raises(ConfigError, match="dataset.ramp_s"):
        SyntheticConfig(camera_path="return", num_frames=60, ramp_s=1.5)  # up and down do not fit in 2 s
    with pytest.raises(ValueError, match="longer than half"):
        synthetic.from_rest(60, ramp_s=1.5)


def _sensor_frame(depth, rgb=None, **fields):
    cfg = SyntheticConfig(**fields)
    rgb = np.full(depth.shape + (3,), 128, np.uint8) if rgb is None else rgb
    h, w = depth.shape
    return sensor.apply(depth, rgb, 200.0, 200.0, (w - 1) / 2, (h - 1) / 2, cfg.sensor_model(),
                        np.random.default_rng(0))


def test_structured_light_noise_grows_with_the_square_of_the_distance_and_is_quantised():
    """A wall facing the camera at 1 m and at 3 m: the depth error's spread follows
    a + b (z - 0.4)^2 (within the quantisation's share), and every depth is f b / (k step)."""
    cfg = SyntheticConfig()
    fb = cfg.sensor_focal_px * cfg.sensor_baseline_m
    spreads = {}
    for z in (1.0, 3.0):
        depth, _ = _sensor_frame(np.full((200, 200), z, np.float32))
        valid = depth > 0
        assert valid.mean() > 0.97  # a flat frontal wall loses only the border's ring
        steps = fb / depth[valid] / cfg.sensor_disparity_step_px
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)
        spreads[z] = float(np.std(depth[valid] - z))
        sigma = cfg.sensor_axial_sigma_m + cfg.sensor_axial_sigma_per_m2 * (z - 0.4) ** 2
        quantum = z * z * cfg.sensor_disparity_step_px / fb
        assert 0.8 * sigma < spreads[z] < np.hypot(sigma, quantum / np.sqrt(12)) * 1.2
    assert spreads[3.0] > 5 * spreads[1.0]


def test_structured_light_loses_depth_at_edges_grazing_and_dark_surfaces():
    h, w = 120, 160
    v, u = np.mgrid[0:h, 0:w]
    # a box 1 m away in front of a wall 2.5 m away; a floor seen at grazing incidence below
    depth = np.full((h, w), 2.5)
    box = (abs(u - 80) < 20) & (abs(v - 40) < 20)
    depth[box] = 1.0
    rows = np.arange(h)[:, None] >= 100
    depth = np.where(rows, 2.5 + (v - 99) * 0.6, depth)  # steep: the floor recedes fast
    rgb = np.full((h, w, 3), 128, np.uint8)
    rgb[:30, :30] = 0  # a black patch on the wall
    out, colour = _sensor_frame(depth.astype(np.float32), rgb)
    ring = box & ~((abs(u - 80) < 18) & (abs(v - 40) < 18))
    assert (out[ring] == 0).mean() > 0.15  # the box's outline
    assert (out[(abs(u - 80) < 15) & (abs(v - 40) < 15)] > 0).all()  # its inside
    assert (out[105:, :] == 0).mean() > 0.9  # grazing
    assert (out[2:28, 2:28] == 0).all() and (out[60:90, 2:28] > 0).all()  # dark, not grey
    assert 1.5 < np.std(colour.astype(float) - rgb) < 2.5


def test_a_structured_light_sequence_is_the_same_every_load(tmp_path):
    cfg = SyntheticConfig(cache_dir=str(tmp_path), depth_model="structured_light", camera_path="room_loop", **SMALL)
    a, b = SyntheticDataset(cfg), SyntheticDataset(cfg)
    np.testing.assert_array_equal(a[3].depth, b[3].depth)
    np.testing.assert_array_equal(a[3].rgb, b[3].rgb)
    clean = SyntheticDataset(SyntheticConfig(cache_dir=str(tmp_path), depth_noise=0.0, camera_path="room_loop",
                                             **SMALL))
    np.testing.assert_array_equal(a[3].gt_pose, clean[3].gt_pose)
    assert 0 < (a[3].depth == 0).mean() < 0.2 and not np.array_equal(a[3].rgb, clean[3].rgb)
