"""The G-ICP tracker's compiled kernels agree with the numpy reference: the same k-NN neighbours
(ties broken by index) and so the same covariances on real frames, the same normal equations and
trial costs (singular combined covariances included), results independent of the thread count,
and a clear fallback without a compiler."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

import slamkit_plugins.trackers.gicp.kernels as kernels_module
from slamkit.errors import ConfigError
from slamkit.geometry.gaussians import knn_covariances, regularize
from slamkit.geometry.transforms import backproject, covariance_from_scales, make_pose, so3_exp
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset
from slamkit_plugins.trackers.gicp.kernels import CompiledKernels, Kernels, NumpyKernels, create_kernels


@pytest.fixture(scope="module")
def library():
    lib = kernels_module.LIBRARY.get()
    if lib is None:
        if shutil.which(os.environ.get("CXX", "c++")) is None:
            pytest.skip("no C++ compiler: the numpy kernels are used")
        pytest.fail(f"a compiler is present but the G-ICP kernels did not build: {kernels_module.LIBRARY.error}")
    return lib


@pytest.fixture(scope="module")
def tum_frames():
    from support.data import TUM, require_data

    dataset = TUMDataset(TUMConfig(path=str(require_data(TUM))))
    return [dataset[i] for i in (0, 40, 120)]


def test_knn_ties_go_to_the_lower_index():
    # A square grid: each point's 4 diagonal neighbours tie; with k = 6 two of them are taken.
    g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0), indexing="ij"), -1).reshape(-1, 2)
    pts = np.concatenate([g, np.zeros((25, 1))], axis=1).astype(np.float32)
    centre = 12
    cov = knn_covariances(pts, k=6, query=np.array([centre]))[0]
    # self, 4 edge neighbours (rows 7, 11, 13, 17), then diagonals 6 and 8 (lowest indices)
    chosen = pts[[12, 7, 11, 13, 17, 6]].astype(np.float64)
    ref = (chosen - chosen.mean(0)).T @ (chosen - chosen.mean(0)) / 6
    np.testing.assert_allclose(cov, ref, atol=1e-12)


@pytest.mark.parametrize("half_window", [1, kernels_module.GRID_HALF_WINDOW])
def test_frame_covariances_equal_the_reference_on_real_frames(library, tum_frames, monkeypatch, half_window):
    """With the default window and a 3x3 one (most points then unproven: every point searched)."""
    monkeypatch.setattr(kernels_module, "GRID_HALF_WINDOW", half_window)
    compiled = CompiledKernels(library, num_threads=2)
    for frame in tum_frames:
        points, pix = backproject(np.asarray(frame.depth), frame.camera, 5)
        ref = NumpyKernels().frame_covariances(points, pix, frame.camera, 5, 10)
        got = compiled.frame_covariances(points, pix, frame.camera, 5, 10)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-18)


def test_grid_search_proves_most_points(library, tum_frames):
    """The window search settles most points itself (else it would only add cost)."""
    frame = tum_frames[1]
    points, pix = backproject(np.asarray(frame.depth), frame.camera, 5)
    n = len(points)
    gh, gw = -(-frame.camera.height // 5), -(-frame.camera.width // 5)
    v, u = np.divmod(pix, frame.camera.width)
    cell = ((v // 5) * gw + u // 5).astype(np.int32)
    grid = np.full(gh * gw, -1, dtype=np.int32)
    grid[cell] = np.arange(n, dtype=np.int32)
    cov, exact = np.empty((n, 3, 3)), np.empty(n, dtype=np.uint8)
    library.slk_grid_knn_covariances(n, points.ctypes.data, cell.ctypes.data, grid.ctypes.data, gh, gw, 10,
                                     kernels_module.GRID_HALF_WINDOW, frame.camera.fx, frame.camera.fy, 5.0,
                                     cov.ctypes.data, exact.ctypes.data, 1)
    assert exact.mean() > 0.9


def test_compiled_regularization_equals_the_reference(library, tum_frames):
    """The ellipse rule on real frame covariances and on the awkward cases (nearly repeated and
    zero eigenvalues, rank 1, negative rounding, non-finite, min_median): the reference's result
    to rounding (libm's acos / cos may differ from numpy's by an ulp); other rules are the
    reference's own. Most real covariances come out bit-identical."""
    rng = np.random.default_rng(8)
    frame = tum_frames[1]
    points, pix = backproject(np.asarray(frame.depth), frame.camera, 5)
    compiled, reference = CompiledKernels(library), NumpyKernels()
    real = reference.frame_covariances(points, pix, frame.camera, 5, 10)
    odd = covariance_from_scales(rng.normal(size=(12, 4)), np.exp(rng.uniform(-8, -2, size=(12, 3))))
    odd[0] = np.eye(3) * 2e-4  # repeated eigenvalues: the reference's accurate path
    odd[1] = np.diag([1e-4, 1e-4 * (1 + 1e-6), 3e-4])  # a nearly repeated pair
    odd[2] = 0.0  # coincident neighbours
    v = rng.normal(size=3)
    odd[3] = np.outer(v, v)  # collinear neighbours: rank 1
    odd[4] = np.diag([-1e-19, 1e-5, 2e-5])  # rounding below zero
    odd[5, 0, 0] = np.nan
    odd[6] = np.diag([1e-6, 2e-6, 1e-3])  # median below min_median
    for cov, tolerance in ((real, 1e-13), (odd, 1e-10)):
        for method, min_median in (("ellipse", None), ("ellipse", 1e-5), ("plane", None), ("none", None)):
            ref = reference.regularize(cov, method, 1e-3, min_median)
            got = compiled.regularize(cov, method, 1e-3, min_median)
            np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
            # an ulp of acos moves the eigenvalues by an ulp of the largest one: relative to
            # each matrix's largest entry (more where the spectrum spans decades, as odd[6])
            scale = np.maximum(np.nanmax(np.abs(ref), axis=(1, 2)), 1e-300)[:, None, None]
            assert np.nanmax(np.abs(got - ref) / scale) <= tolerance
    assert np.array_equal(compiled.regularize(odd, "ellipse", 1e-3)[2], np.eye(3))
    same = np.all(compiled.regularize(real, "ellipse", 1e-3) == reference.regularize(real, "ellipse", 1e-3),
                  axis=(1, 2))
    assert same.mean() > 0.5


def _problem(rng, n=3000, n_target=2000, degenerate=50):
    """Source rows (p, C_s) near target rows (mu, C_t), some targets degenerate (rank 1 or 0)."""
    mu = rng.uniform(-1, 1, size=(n_target, 3)) + [0, 0, 3]
    cov_t = regularize(covariance_from_scales(rng.normal(size=(n_target, 4)),
                                              np.exp(rng.uniform(-6, -2, size=(n_target, 3)))), "ellipse")
    cov_t[:degenerate] = 0.0
    cov_t[degenerate:2 * degenerate] = np.einsum("ni,nj->nij", *(2 * [rng.normal(size=(degenerate, 3))]))
    T = make_pose(so3_exp(np.array([0.1, -0.2, 0.05])), np.array([0.2, 0.1, -0.3]))
    nn = rng.integers(0, n_target, size=n).astype(np.uint32)
    nn[rng.random(n) < 0.2] = n_target  # unmatched
    p_world = mu[np.minimum(nn, n_target - 1)] + rng.normal(scale=0.01, size=(n, 3))
    p = (p_world - T[:3, 3]) @ T[:3, :3]
    cov_s = regularize(covariance_from_scales(rng.normal(size=(n, 4)), np.exp(rng.uniform(-6, -2, size=(n, 3)))),
                       "ellipse")
    cov_s[:degenerate] = 0.0  # with a zero target covariance: a singular sum
    src = np.concatenate([p, cov_s.reshape(n, 9)], axis=1)
    target = np.concatenate([mu, cov_t.reshape(n_target, 9)], axis=1)
    return src, target, nn, T


def test_linearization_equals_the_reference(library):
    rng = np.random.default_rng(3)
    src, target, nn, T = _problem(rng)
    ref = NumpyKernels().linearize(src, target, nn, T)
    got = CompiledKernels(library).linearize(src, target, nn, T)
    assert got.matched == ref.matched and got.singular == ref.singular > 0
    scale = np.abs(ref.H).max()
    np.testing.assert_allclose(got.H, ref.H, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(got.g, ref.g, rtol=1e-9, atol=1e-9 * np.abs(ref.g).max())
    assert got.cost == pytest.approx(ref.cost, rel=1e-9)
    Tn = T @ make_pose(so3_exp(np.array([0.01, 0.0, -0.02])), np.array([0.005, -0.01, 0.0]))
    assert got.cost_at(Tn) == pytest.approx(ref.cost_at(Tn), rel=1e-9)
    assert got.cost_at(T) == pytest.approx(got.cost, rel=1e-12)


def test_results_do_not_depend_on_the_thread_count(library):
    rng = np.random.default_rng(4)
    src, target, nn, T = _problem(rng, n=5000)
    one = CompiledKernels(library, num_threads=1).linearize(src, target, nn, T)
    three = CompiledKernels(library, num_threads=3).linearize(src, target, nn, T)
    assert np.array_equal(one.H, three.H) and np.array_equal(one.g, three.g) and one.cost == three.cost
    assert one.cost_at(T @ make_pose(np.eye(3), np.array([0.01, 0, 0]))) == \
        three.cost_at(T @ make_pose(np.eye(3), np.array([0.01, 0, 0])))


def test_without_a_compiler_auto_falls_back_and_compiled_says_why(monkeypatch, tmp_path):
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    monkeypatch.setattr(kernels_module, "LIBRARY", kernels_module.new_library())  # built again, without a compiler
    with pytest.warns(RuntimeWarning, match="numpy kernels"):
        assert isinstance(create_kernels(Kernels.auto), NumpyKernels)
    with pytest.raises(ConfigError, match="no C\\+\\+ compiler found"):
        create_kernels(Kernels.compiled)
    assert create_kernels(Kernels.numpy).name == "numpy"


def _brute_force_nearest(means, queries, max_distance):
    """The nearest mean by (float32 squared distance summed x, y, z in turn, index) within
    max_distance: (squared distances, inf where none; indices, len(means) where none)."""
    diff = queries[:, None, :] - means[None, :, :]  # float32
    d2 = (diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]) + diff[..., 2] * diff[..., 2]
    best = np.argmin(d2, axis=1)  # the first (lowest index) of equal minima
    best_d2 = d2[np.arange(len(queries)), best]
    inside = best_d2 <= np.float32(max_distance) ** 2
    return np.where(inside, best_d2, np.float32(np.inf)), np.where(inside, best, len(means)).astype(np.uint32)


def _hints(rng, reference_idx, n):
    """No hint, the right answer, and random hints (some out of range: none)."""
    return (None, reference_idx, rng.integers(0, n + 5, size=len(reference_idx)).astype(np.uint32))


@pytest.mark.parametrize("cell_factor", [0.3, 1.0, 2.0, 7.0])
def test_compiled_grid_equals_brute_force_with_ties(library, cell_factor):
    """Means and queries on a 1 cm lattice (many equal distances, duplicate means): the grid
    returns the lowest-index mean among the nearest, for any cell size, distance and hint."""
    from slamkit_plugins.trackers.gicp.kernels import CompiledGrid

    rng = np.random.default_rng(11)
    means = (rng.integers(0, 20, size=(1500, 3)) * 0.01).astype(np.float32)
    means[1000:1100] = means[:100]  # duplicates: the lower index wins
    queries = (rng.integers(-3, 23, size=(2000, 3)) * 0.01).astype(np.float32)
    queries[:50] = means[1000:1050]  # exactly on a duplicated mean
    for max_distance in (0.005, 0.01, 0.03, 0.1):
        ref_d2, ref_idx = _brute_force_nearest(means, queries, max_distance)
        grid = CompiledGrid(library, means, cell_factor * max_distance, num_threads=2)
        for hint in _hints(rng, ref_idx, len(means)):
            d2, idx = grid.nearest(queries, max_distance, hint=hint)
            np.testing.assert_array_equal(idx, ref_idx)
            np.testing.assert_array_equal(d2, ref_d2)
    assert np.all(_brute_force_nearest(means, queries[:50], 0.01)[1] < 100)


def test_compiled_grid_equals_pykdtree_on_random_clouds(library):
    """Continuous random means (a wide box, a thin slab) and queries: the same matches as pykdtree,
    at the grid's own distance and at three times it (the coarse-to-fine fallback's)."""
    from slamkit_plugins.trackers.gicp.kernels import CompiledGrid, PyKDTreeIndex

    rng = np.random.default_rng(12)
    for scale in ([2.0, 2.0, 2.0], [3.0, 3.0, 0.02]):
        means = (rng.uniform(-1, 1, size=(20000, 3)) * scale + [0, 0, 2]).astype(np.float32)
        queries = (means[rng.choice(len(means), 5000)] + rng.normal(scale=0.03, size=(5000, 3))).astype(np.float32)
        grid = CompiledGrid(library, means, 0.06, num_threads=1)
        for max_distance in (0.03, 0.09):
            ref_d2, ref_idx = PyKDTreeIndex(means).nearest(queries, max_distance)
            for hint in _hints(rng, ref_idx, len(means)):
                d2, idx = grid.nearest(queries, max_distance, hint=hint)
                np.testing.assert_array_equal(idx, ref_idx)
                np.testing.assert_array_equal(d2, ref_d2)


def test_compiled_grid_answers_far_and_non_finite_queries_with_none(library):
    from slamkit_plugins.trackers.gicp.kernels import CompiledGrid

    means = np.array([[0, 0, 1], [0.01, 0, 1]], dtype=np.float32)
    queries = np.array([[0, 0, 1.001], [50, 0, 1], [np.nan, 0, 1], [np.inf, 0, 0], [0.02, 0, 1]], dtype=np.float32)
    d2, idx = CompiledGrid(library, means, 0.06).nearest(queries, 0.03)
    assert idx.tolist() == [0, 2, 2, 2, 1]
    assert np.isinf(d2[1:4]).all() and d2[0] == pytest.approx(1e-6, rel=1e-3)
    d2, idx = CompiledGrid(library, np.zeros((0, 3), np.float32), 0.06).nearest(queries, 0.03)
    assert idx.tolist() == [0] * 5 and np.isinf(d2).all()
    with_nan = np.array([[0, 0, 1], [np.nan, 0, 1], [0.01, 0, 1]], dtype=np.float32)
    assert CompiledGrid(library, with_nan, 0.06).nearest(queries, 0.03)[1].tolist() == [0, 3, 3, 3, 2]


def test_compiled_grid_over_a_huge_box_uses_coarser_cells_and_stays_exact(library):
    """Means spread over kilometres (more cells than the grid holds at the asked size)."""
    from slamkit_plugins.trackers.gicp.kernels import CompiledGrid

    rng = np.random.default_rng(13)
    means = rng.uniform(-2000, 2000, size=(3000, 3)).astype(np.float32)
    queries = (means[rng.choice(3000, 1000)] + rng.normal(scale=0.02, size=(1000, 3))).astype(np.float32)
    ref_d2, ref_idx = _brute_force_nearest(means, queries, 0.03)
    d2, idx = CompiledGrid(library, means, 0.06).nearest(queries, 0.03)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_array_equal(d2, ref_d2)


def test_compiled_nearest_neighbours_equal_pykdtree(library, tum_frames):
    """Real map-like points (a frame's back-projection) and queries offset by up to ~4 cm: the
    same matches within 3 cm as pykdtree, with or without a hint (a wrong hint included)."""
    from slamkit_plugins.trackers.gicp.kernels import PyKDTreeIndex

    rng = np.random.default_rng(5)
    frame = tum_frames[0]
    means, _ = backproject(np.asarray(frame.depth), frame.camera, 3)
    queries = (means[rng.choice(len(means), 4000)] + rng.normal(scale=0.02, size=(4000, 3))).astype(np.float32)
    ref_d2, ref_idx = PyKDTreeIndex(means).nearest(queries, 0.03)
    index = CompiledKernels(library, num_threads=2).nearest_index(means, 0.03)
    for hint in _hints(rng, ref_idx, len(means)):
        d2, idx = index.nearest(queries, 0.03, hint=hint)
        assert np.array_equal(idx, ref_idx)
        np.testing.assert_array_equal(d2, ref_d2)
    assert 0.2 < np.mean(ref_idx < len(means)) < 1.0  # both matched and unmatched queries


def test_compiled_tracking_equals_numpy_tracking_on_real_frames(tum_frames):
    """Same trajectory from both kernel sets over a few real frames (map = first frame)."""
    from slamkit.map.gaussian_map import GaussianMap
    from slamkit.map.growth import MapGrowthConfig
    from slamkit.registry.discovery import default_registry
    from slamkit.run.slam import SLAM

    from support.data import TUM

    dataset = TUMDataset(TUMConfig(path=str(TUM), max_frames=12))
    frames = [dataset[i] for i in range(len(dataset))]
    registry = default_registry()
    poses = {}
    for kernels in ("numpy", "compiled"):
        if kernels == "compiled" and kernels_module.LIBRARY.get() is None:
            pytest.skip("no compiled kernels")
        slam = SLAM(registry.create("tracker", "gicp", registry.get("tracker", "gicp").config(kernels=kernels)),
                    registry.create("keyframe", "overlap", registry.get("keyframe", "overlap").config()),
                    registry.create("mapper", "none", registry.get("mapper", "none").config()), GaussianMap(),
                    MapGrowthConfig())
        slam.initialize(frames[0].gt_pose)
        poses[kernels] = np.array([slam.process(f).tracking.pose for f in frames])
    np.testing.assert_allclose(poses["compiled"], poses["numpy"], atol=1e-9)
