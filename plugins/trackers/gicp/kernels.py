"""The G-ICP tracker's hot loops, in numpy (the reference) and compiled (csrc/gicp_kernels.cpp),
giving the same results (tests/plugins/test_gicp_kernels.py checks them against each other):

- `frame_covariances`: each back-projected point's k-NN covariance; the compiled version searches
  a window of the pixel grid and proves the result exact by a projection bound, else searches
  all points.
- `nearest_index`: the target means' nearest-neighbour search within the correspondence distance,
  built once per tracking keyframe: pykdtree, or a compiled uniform grid that starts from the last
  match (float32 distances as pykdtree's, ties to the lower index).
- `regularize`: the compiled version does the ellipse rule in one pass and leaves the covariances
  with a nearly repeated eigenvalue pair to the numpy reference.
- `linearize`: one Levenberg-Marquardt step's normal equations H, g and cost at a pose, and the
  cost of trial poses with the same correspondences.
"""

from __future__ import annotations

import ctypes
import enum
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from pykdtree.kdtree import KDTree

from slamkit.errors import ConfigError
from slamkit.geometry.gaussians import Regularization, knn_covariances, regularize, whitening_sym3
from slamkit.native import NativeLibrary, available_threads

SOURCE = Path(__file__).resolve().parent / "csrc" / "gicp_kernels.cpp"
ABI_VERSION = 6
#: Window half-width (grid cells) of the compiled k-NN search: up to 25x25 cells around each point
#: (a point it cannot prove exact there searches every point; docs/results.md, "Tracking per frame").
GRID_HALF_WINDOW = 12
#: Points per pykdtree leaf (the numpy kernels' nearest-neighbour index).
KDTREE_LEAF_SIZE = 16
#: The compiled nearest-neighbour grid's cell edge, in units of the correspondence distance.
GRID_CELL_FACTOR = 2.0
#: Condition number beyond which a combined covariance is inverted as a pseudo-inverse.
MAX_CONDITION = 1e10


class Kernels(enum.Enum):
    """auto: compiled when a C++ compiler builds them, else numpy (with a one-line warning).
    compiled: the compiled kernels or an error. numpy: the numpy reference."""

    auto = "auto"
    compiled = "compiled"
    numpy = "numpy"


@dataclass
class Linearization:
    """Normal equations at a pose: H (6,6), g (6,) and cost = sum r^T W r over `matched`
    correspondences (`singular` of whose combined covariances were pseudo-inverted). `cost_at(T)`
    is the cost at another pose (4x4 camera-to-world) with the same correspondences and weights."""

    H: np.ndarray
    g: np.ndarray
    cost: float
    matched: int
    singular: int
    cost_at: Callable[[np.ndarray], float]


def _declare(lib) -> None:
    P, I, D = ctypes.c_void_p, ctypes.c_int, ctypes.c_double
    lib.slk_grid_knn_covariances.restype = None
    lib.slk_grid_knn_covariances.argtypes = [I, P, P, P, I, I, I, I, D, D, D, P, P, I]
    lib.slk_regularize_ellipse.restype = None
    lib.slk_regularize_ellipse.argtypes = [I, P, D, P, P, I]
    lib.slk_gicp_linearize.restype = I
    lib.slk_gicp_linearize.argtypes = [I, P, I, P, P, P, P, D, P, P, P, P, P, P, I]
    lib.slk_gicp_cost.restype = D
    lib.slk_gicp_cost.argtypes = [I, P, P, P, P, P, P, I]
    lib.slk_grid_build.restype = P
    lib.slk_grid_build.argtypes = [I, P, D]
    lib.slk_grid_free.restype = None
    lib.slk_grid_free.argtypes = [P]
    lib.slk_grid_nearest.restype = None
    lib.slk_grid_nearest.argtypes = [P, I, P, ctypes.c_float, P, P, P, I]


def new_library() -> NativeLibrary:
    """A handle on the kernels' library, not built yet (it builds on its first `get()`)."""
    return NativeLibrary(SOURCE, "G-ICP kernels", ABI_VERSION, _declare)


#: The library the kernels use (built on first use, tried once per process).
LIBRARY = new_library()


def _ptr(a: np.ndarray) -> int:
    return a.ctypes.data


class NumpyKernels:
    """The reference implementation (vectorised numpy)."""

    name = "numpy"

    def __init__(self, num_threads: int = 1):
        self.num_threads = num_threads

    def frame_covariances(self, points: np.ndarray, pix: np.ndarray, camera, stride: int, k: int) -> np.ndarray:
        """(N,3,3) k-NN covariances (m^2) of camera-frame points (N,3) back-projected at flat
        pixel indices `pix` of every `stride`-th pixel."""
        return knn_covariances(points, k)

    def regularize(self, cov: np.ndarray, method: Regularization, eps: float,
                   min_median: float | None = None) -> np.ndarray:
        """(N,3,3) covariances (m^2) regularised for G-ICP (slamkit.geometry.gaussians.regularize)."""
        return regularize(cov, method, eps, min_median=min_median)

    def nearest_index(self, means: np.ndarray, max_distance: float) -> "NearestIndex":
        """A nearest-neighbour index over (N,3) float32 target means (metres) for searches
        within about `max_distance` metres (any distance is answered; this one fastest)."""
        return PyKDTreeIndex(means)

    def linearize(self, src: np.ndarray, target: np.ndarray, nn: np.ndarray, T: np.ndarray) -> Linearization:
        """src: (n,12) rows (p, C_s) in the camera frame; target: (N,12) rows (mu, C_t) in the
        world frame; nn: (n,) target row of each source point (>= N: none); T: the pose.

        Residuals r_i = R^T (mu_i - R p_i - t) (body frame), W_i = (R^T C_t,i R + C_s,i)^-1 =
        G_i^T G_i (G_i: inverse Cholesky factor; pseudo-inverse where singular), and
        dr_i/dxi = [[p_i]x, -I] for T <- T exp(xi), xi = (omega, v)."""
        valid = nn < len(target)
        m = int(np.count_nonzero(valid))
        R, t = T[:3, :3], T[:3, 3]
        tg, sg = target[nn[valid]], src[valid]
        p = sg[:, :3]
        q = (tg[:, :3] - t) @ R  # R^T (mu - t)
        G, singular = whitening_sym3(_rotate_rows(R, tg[:, 3:], m) + sg[:, 3:].reshape(m, 3, 3), MAX_CONDITION)
        z = np.einsum("nij,nj->ni", G, q - p)  # whitened residuals: |z|^2 = r^T W r
        # Whitened Jacobian A = G [S, -I] with S = [p]x: the rows of G S are the rows of G
        # crossed with p. H = A^T A and g = A^T z by one matrix product each.
        A = np.empty((m, 3, 6))
        px, py, pz = p[:, 0], p[:, 1], p[:, 2]
        for i in range(3):
            gx, gy, gz = G[:, i, 0], G[:, i, 1], G[:, i, 2]
            A[:, i, 0] = gy * pz - gz * py
            A[:, i, 1] = gz * px - gx * pz
            A[:, i, 2] = gx * py - gy * px
        np.negative(G, out=A[:, :, 3:])
        A = A.reshape(-1, 6)

        def cost_at(Tn: np.ndarray) -> float:
            # R^T (mu - Rn p - tn) = R^T (mu - t) - R^T (tn - t) - (R^T Rn) p
            rn = q - (Tn[:3, 3] - t) @ R - p @ (R.T @ Tn[:3, :3]).T
            zn = np.einsum("nij,nj->ni", G, rn)
            return float(np.einsum("ni,ni->", zn, zn))

        return Linearization(A.T @ A, A.T @ z.reshape(-1), float(np.einsum("ni,ni->", z, z)), m,
                             int(singular.sum()), cost_at)


class CompiledKernels(NumpyKernels):
    """The same results from csrc/gicp_kernels.cpp (C++ via ctypes, `num_threads` threads)."""

    name = "compiled"

    def __init__(self, lib, num_threads: int = 1):
        super().__init__(num_threads)
        self.lib = lib

    def frame_covariances(self, points: np.ndarray, pix: np.ndarray, camera, stride: int, k: int) -> np.ndarray:
        n = len(points)
        if n <= k:
            return knn_covariances(points, k)
        pts = np.ascontiguousarray(points, dtype=np.float32)
        gh, gw = -(-camera.height // stride), -(-camera.width // stride)
        v, u = np.divmod(np.asarray(pix, dtype=np.int64), camera.width)
        cell = ((v // stride) * gw + u // stride).astype(np.int32)
        grid = np.full(gh * gw, -1, dtype=np.int32)
        grid[cell] = np.arange(n, dtype=np.int32)
        cov = np.empty((n, 3, 3))
        exact = np.empty(n, dtype=np.uint8)
        self.lib.slk_grid_knn_covariances(n, _ptr(pts), _ptr(cell), _ptr(grid), gh, gw, k, GRID_HALF_WINDOW,
                                          float(camera.fx), float(camera.fy), float(stride), _ptr(cov), _ptr(exact),
                                          self.num_threads)
        return cov

    def regularize(self, cov: np.ndarray, method: Regularization, eps: float,
                   min_median: float | None = None) -> np.ndarray:
        cov = np.ascontiguousarray(cov, dtype=np.float64)
        n = len(cov)
        if Regularization(method) is not Regularization.ellipse or n == 0:
            return super().regularize(cov, method, eps, min_median)
        out, redo = np.empty_like(cov), np.empty(n, dtype=np.uint8)
        self.lib.slk_regularize_ellipse(n, _ptr(cov), np.nan if min_median is None else float(min_median),
                                        _ptr(out), _ptr(redo), self.num_threads)
        rest = np.flatnonzero(redo)
        if len(rest):
            out[rest] = super().regularize(cov[rest], method, eps, min_median)
        return out

    def nearest_index(self, means: np.ndarray, max_distance: float) -> "NearestIndex":
        return CompiledGrid(self.lib, means, GRID_CELL_FACTOR * max_distance, self.num_threads)

    def linearize(self, src: np.ndarray, target: np.ndarray, nn: np.ndarray, T: np.ndarray) -> Linearization:
        n = len(src)
        nn = np.ascontiguousarray(nn, dtype=np.uint32)
        R = np.ascontiguousarray(T[:3, :3])
        t = np.ascontiguousarray(T[:3, 3])
        H, g, stats = np.empty((6, 6)), np.empty(6), np.empty(3)
        sel = np.empty(n, dtype=np.int32)
        q, W = np.empty((n, 3)), np.empty((n, 6))
        m = self.lib.slk_gicp_linearize(n, _ptr(src), len(target), _ptr(target), _ptr(nn), _ptr(R), _ptr(t),
                                        MAX_CONDITION, _ptr(H), _ptr(g), _ptr(sel), _ptr(q), _ptr(W), _ptr(stats),
                                        self.num_threads)

        def cost_at(Tn: np.ndarray) -> float:
            A = np.ascontiguousarray(R.T @ Tn[:3, :3])
            b = np.ascontiguousarray((Tn[:3, 3] - t) @ R)
            return self.lib.slk_gicp_cost(m, _ptr(src), _ptr(sel), _ptr(q), _ptr(W), _ptr(A), _ptr(b),
                                          self.num_threads)

        return Linearization(H, g, float(stats[0]), int(m), int(stats[2]), cost_at)


class NearestIndex:
    """Nearest target mean of each query point within a distance."""

    def nearest(self, queries: np.ndarray, max_distance: float, hint: np.ndarray | None = None):
        """queries: (m,3) float32 (metres, world frame); hint: (m,) a candidate index per query
        (e.g. the last match; >= N: none). Returns (squared distances (m,) float32, inf where
        none; indices (m,) uint32, N where none within max_distance)."""
        raise NotImplementedError


class PyKDTreeIndex(NearestIndex):
    def __init__(self, means: np.ndarray):
        self.tree = KDTree(np.ascontiguousarray(means, dtype=np.float32), leafsize=KDTREE_LEAF_SIZE)
        self.size = len(means)

    def nearest(self, queries, max_distance, hint=None):
        d2, idx = self.tree.query(queries, k=1, distance_upper_bound=max_distance, sqr_dists=True)
        return np.where(idx < self.size, d2, np.inf).astype(np.float32), idx


class CompiledGrid(NearestIndex):
    """csrc/gicp_kernels.cpp's grid of `cell_size`-metre cells over the means (freed with this
    object). Any search distance is answered exactly; one close to the cell size is fastest."""

    def __init__(self, lib, means: np.ndarray, cell_size: float, num_threads: int = 1):
        if not cell_size > 0:
            raise ValueError(f"grid cell size: expected > 0 metres, got {cell_size}")
        self.lib, self.num_threads = lib, num_threads
        self.means = np.ascontiguousarray(means, dtype=np.float32)
        self.size = len(self.means)
        self.handle = lib.slk_grid_build(self.size, _ptr(self.means), float(cell_size))

    def nearest(self, queries, max_distance, hint=None):
        q = np.ascontiguousarray(queries, dtype=np.float32)
        m = len(q)
        idx, d2 = np.empty(m, dtype=np.uint32), np.empty(m, dtype=np.float32)
        h = None if hint is None else np.ascontiguousarray(hint, dtype=np.uint32)
        self.lib.slk_grid_nearest(self.handle, m, _ptr(q), np.float32(max_distance) ** 2,
                                  None if h is None else _ptr(h), _ptr(idx), _ptr(d2), self.num_threads)
        return d2, idx

    def __del__(self):
        handle, self.handle = getattr(self, "handle", None), None
        if handle:
            self.lib.slk_grid_free(handle)


def _rotate_rows(R: np.ndarray, cov_rows: np.ndarray, m: int) -> np.ndarray:
    """R^T C R for (m,9) row-major covariances C: (m,3,3)."""
    CR = (cov_rows.reshape(m * 3, 3) @ R).reshape(m, 3, 3)
    return (R.T @ CR.transpose(1, 0, 2).reshape(3, m * 3)).reshape(3, m, 3).transpose(1, 0, 2)


def create_kernels(choice: Kernels, num_threads: int = 0) -> NumpyKernels:
    """The kernels `choice` asks for, with `num_threads` threads (0: `available_threads()`).
    `auto` without a working compiler warns once and gives numpy; `compiled` without one raises
    ConfigError (one line, exit status 2) with the reason."""
    choice = Kernels(choice)
    num_threads = num_threads or available_threads()
    if choice is Kernels.numpy:
        return NumpyKernels(num_threads)
    lib = LIBRARY.get()
    if lib is not None:
        return CompiledKernels(lib, num_threads)
    if choice is Kernels.compiled:
        raise ConfigError(f"tracker.kernels=compiled: the G-ICP kernels are not available ({LIBRARY.error})")
    _warn_once(f"slamkit: G-ICP kernels not compiled ({LIBRARY.error}); using the numpy kernels (slower)")
    return NumpyKernels(num_threads)


_WARNED: set[str] = set()


def _warn_once(message: str) -> None:
    if message not in _WARNED:
        _WARNED.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)
