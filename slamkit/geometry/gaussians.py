"""Gaussian geometry shared by tracking and mapping: k-NN covariances, closed-form batched
3x3 symmetric eigenvalues / eigenvectors (faster than ``np.linalg.eigh`` on many small matrices:
docs/dependencies.md, "Written here, and why"), covariance regularisation (paper Sec. 3.1), batched
3x3 inverses and whitening (inverse Cholesky) with a pseudo-inverse fallback, and covariance
rotation.

All functions are vectorised numpy (no Python loop over points). Covariances are (N,3,3) in
m^2; points (N,3) in metres.
"""

from __future__ import annotations

import enum

import numpy as np
from pykdtree.kdtree import KDTree

#: Extra neighbours fetched so that ties at the k-th distance can be broken by index.
TIE_SPARE = 6


class Regularization(enum.Enum):
    """How covariances are regularised before G-ICP (paper Sec. 3.1, Table 5).

    ellipse: eigenvalues divided by the median eigenvalue (shape kept, median axis 1).
    plane: eigenvalues replaced by (1, 1, eps), eps on the smallest axis.
    none: raw covariances.
    """

    ellipse = "ellipse"
    plane = "plane"
    none = "none"


def knn_covariances(points: np.ndarray, k: int = 10, tree: KDTree | None = None,
                    query: np.ndarray | None = None) -> np.ndarray:
    """Covariance of each point's k nearest neighbours (the point itself included):
    (1/k) sum_j (p_j - mu)(p_j - mu)^T, with mu the neighbours' mean.

    points: (N,3). tree: a pykdtree KDTree over `points` (built here when None). query: indices
    of the points whose covariance is wanted (all when None). When N < k all N points are used.
    Returns (len(query) or N, 3, 3) float64 (offsets from each point are taken in float64, so
    thin structures keep their small eigenvalues). Neighbours are ordered by (float64 distance,
    index), so ties at the k-th distance (common with quantised depth) do not depend on the
    tree: the compiled tracker kernels pick the same neighbours.
    """
    pts = np.ascontiguousarray(points)
    rows = np.arange(len(pts)) if query is None else np.asarray(query)
    n = len(rows)
    if n == 0 or len(pts) == 0:
        return np.zeros((n, 3, 3))
    k = max(1, min(int(k), len(pts)))
    if tree is None:
        tree = KDTree(pts if pts.dtype in (np.float32, np.float64) else pts.astype(np.float64), leafsize=16)
    at = pts if query is None else pts[rows]
    dtype = tree.data.dtype if hasattr(tree, "data") else at.dtype
    idx = _nearest(pts, rows, tree.query(np.ascontiguousarray(at, dtype=dtype), k=min(k + TIE_SPARE, len(pts)))[1], k)
    # Offsets from the point itself (small numbers, float64), then second moments minus the
    # squared mean: no cancellation worth the name at these magnitudes.
    pt = np.ascontiguousarray(pts.T, dtype=np.float64)  # (3,N)
    g = pt[:, idx]
    g -= pt[:, rows, None]  # (3,n,k)
    m = g.mean(axis=2)  # (3,n)
    cov = np.empty((n, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cij = np.einsum("nk,nk->n", g[i], g[j]) / k - m[i] * m[j]
            cov[:, i, j] = cij
            cov[:, j, i] = cij
    return cov


def _nearest(pts: np.ndarray, rows: np.ndarray, cand: np.ndarray, k: int) -> np.ndarray:
    """The k of each row's candidate neighbours (n, >= k) nearest by (float64 squared distance
    from the float32/64 coordinates, then index)."""
    cand = cand.reshape(len(rows), -1).astype(np.int64)
    p = pts.astype(np.float64, copy=False)
    diff = p[cand] - p[rows][:, None, :]
    d = (diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]) + diff[..., 2] * diff[..., 2]
    order = np.lexsort((cand, d), axis=1)[:, :k]
    return np.take_along_axis(cand, order, axis=1)


def _trig_eigvals(B: np.ndarray):
    """Eigenvalues (min, mid, max) of (N,3,3) symmetric matrices (already scaled to O(1)) by
    the trigonometric formula."""
    a00, a11, a22 = B[:, 0, 0], B[:, 1, 1], B[:, 2, 2]
    a01, a02, a12 = B[:, 0, 1], B[:, 0, 2], B[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0
    p = np.sqrt(p2)
    safe_p = np.where(p > 0, p, 1.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    r = np.clip(det / (2.0 * safe_p**3), -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    l_max = q + 2.0 * p * np.cos(phi)
    l_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return l_min, 3.0 * q - l_max - l_min, l_max


def sym3_eigvals(cov: np.ndarray) -> np.ndarray:
    """Eigenvalues (N,3), ascending, of (N,3,3) symmetric matrices (closed form)."""
    A = np.asarray(cov, dtype=np.float64)
    n = len(A)
    if n == 0:
        return np.zeros((0, 3))
    scale = np.abs(A).reshape(n, 9).max(axis=1)
    scale = np.where(scale > 0, scale, 1.0)
    vals = np.stack(_trig_eigvals(A / scale[:, None, None]), axis=1)
    # The trigonometric formula loses precision (to ~1e-8 of the largest eigenvalue) on a
    # nearly repeated pair; those matrices take the slower, accurate path.
    gaps = np.diff(vals, axis=1).min(axis=1)
    close = gaps < 1e-4 * np.abs(vals).max(axis=1)
    vals *= scale[:, None]
    if close.any():
        vals[close] = sym3_eigh(A[close])[0]
    bad = ~np.isfinite(vals).all(axis=1)
    if bad.any():
        vals[bad] = np.linalg.eigvalsh(np.nan_to_num(A[bad]))
    return vals


def rotate_covariances(R: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """R C R^T for one 3x3 rotation R and (N,3,3) covariances C (two plain matrix products,
    much faster than a batched 3x3 matmul)."""
    n = len(cov)
    CRt = (np.ascontiguousarray(cov).reshape(n * 3, 3) @ R.T).reshape(n, 3, 3)  # C R^T
    return (R @ CRt.transpose(1, 0, 2).reshape(3, n * 3)).reshape(3, n, 3).transpose(1, 0, 2)


def _orthonormal_complement(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N,3) spanning the plane orthogonal to unit vectors v (N,3)."""
    ax, ay = np.abs(v[:, 0]), np.abs(v[:, 1])
    use_x = ax > ay
    u = np.where(
        use_x[:, None],
        np.stack([-v[:, 2], np.zeros_like(ax), v[:, 0]], axis=1),
        np.stack([np.zeros_like(ax), v[:, 2], -v[:, 1]], axis=1),
    )
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(v, u)


def sym3_eigh(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-decomposition of (N,3,3) symmetric matrices, like ``np.linalg.eigh`` (eigenvalues
    ascending, eigenvectors as columns), in closed form for many small matrices.

    Closed form: eigenvalues by the trigonometric formula; the eigenvector of the best isolated
    eigenvalue from cross products of rows of (A - lambda I); the other two from the 2x2
    problem in its orthogonal complement (stable for repeated eigenvalues). Matrices whose
    result is not finite fall back to ``np.linalg.eigh``.
    """
    A = np.asarray(cov, dtype=np.float64)
    n = len(A)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    scale = np.abs(A).reshape(n, 9).max(axis=1)
    scale = np.where(scale > 0, scale, 1.0)
    B = A / scale[:, None, None]
    l_min, l_mid, l_max = _trig_eigvals(B)
    # The eigenvalue farther from the middle one is isolated: its eigenvector is well posed.
    top_isolated = (l_max - l_mid) >= (l_mid - l_min)
    iso = np.where(top_isolated, l_max, l_min)
    r0 = B[:, 0, :].copy()
    r1 = B[:, 1, :].copy()
    r2 = B[:, 2, :].copy()
    r0[:, 0] -= iso
    r1[:, 1] -= iso
    r2[:, 2] -= iso
    c = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)  # (N,3,3)
    norms = np.einsum("nij,nij->ni", c, c)
    best = np.argmax(norms, axis=1)
    v_iso = c[np.arange(n), best]
    nv = np.sqrt(norms[np.arange(n), best])
    isotropic = nv <= 1e-30
    v_iso = np.where(isotropic[:, None], np.array([0.0, 0.0, 1.0]), v_iso / np.where(isotropic, 1.0, nv)[:, None])
    u, w = _orthonormal_complement(v_iso)
    Bu = np.einsum("nij,nj->ni", B, u)
    Bw = np.einsum("nij,nj->ni", B, w)
    m00 = np.einsum("ni,ni->n", u, Bu)
    m11 = np.einsum("ni,ni->n", w, Bw)
    m01 = np.einsum("ni,ni->n", u, Bw)
    theta = 0.5 * np.arctan2(2.0 * m01, m00 - m11)
    ct, st = np.cos(theta)[:, None], np.sin(theta)[:, None]
    big = ct * u + st * w
    small = -st * u + ct * w
    half_sum, half_diff = 0.5 * (m00 + m11), np.sqrt((0.5 * (m00 - m11)) ** 2 + m01 * m01)
    lam_big, lam_small = half_sum + half_diff, half_sum - half_diff
    lam_iso = np.einsum("ni,nij,nj->n", v_iso, B, v_iso)
    t = top_isolated[:, None]
    vals = np.stack(
        [
            np.where(top_isolated, lam_small, lam_iso),
            np.where(top_isolated, lam_big, lam_small),
            np.where(top_isolated, lam_iso, lam_big),
        ],
        axis=1,
    )
    vecs = np.stack(
        [np.where(t, small, v_iso), np.where(t, big, small), np.where(t, v_iso, big)], axis=2
    )
    vals *= scale[:, None]
    bad = ~(np.isfinite(vals).all(axis=1) & np.isfinite(vecs).all(axis=(1, 2)))
    if bad.any():
        vals[bad], vecs[bad] = np.linalg.eigh(np.nan_to_num(A[bad]))
    return vals, vecs


def compose(vecs: np.ndarray, vals: np.ndarray) -> np.ndarray:
    """V diag(vals) V^T for (N,3,3) column eigenvectors and (N,3) eigenvalues."""
    return np.einsum("nik,nk,njk->nij", vecs, vals, vecs, optimize=True)


def regularize(
    cov: np.ndarray,
    method: Regularization | str = Regularization.ellipse,
    eps: float = 1e-3,
    *,
    min_median: float | None = None,
) -> np.ndarray:
    """Regularise (N,3,3) covariances for G-ICP (paper Sec. 3.1).

    ellipse: C = U diag(l1 >= l2 >= l3) U^T becomes U diag(l1/l2, 1, l3/l2) U^T, dividing by
      the median (sorted) eigenvalue. With `min_median` (m^2) set, a covariance whose median
      eigenvalue is below it becomes min_median * I instead (the reference code's rule for map
      Gaussians; not applied to frame covariances, whose median is far below it). A
      covariance with a zero median eigenvalue (collinear or coincident neighbours) becomes I.
    plane: eigenvalues become (1, 1, eps), eps on the smallest axis.
    none: returned unchanged (a float64 copy).
    """
    method = Regularization(method)
    cov = np.asarray(cov, dtype=np.float64)
    if method is Regularization.none or len(cov) == 0:
        return cov.copy()
    if method is Regularization.plane:
        # V diag(eps, 1, 1) V^T = I - (1 - eps) v_min v_min^T.
        _, vecs = sym3_eigh(cov)
        v = vecs[:, :, 0]
        return np.eye(3) - (1.0 - eps) * (v[:, :, None] * v[:, None, :])
    # ellipse: dividing every eigenvalue by the median one is dividing the matrix by it.
    vals = sym3_eigvals(cov)  # ascending: l3, l2, l1
    median = vals[:, 1]
    degenerate = ~(median > 1e-12 * np.maximum(vals[:, 2], 1e-300))
    out = cov / np.where(degenerate, 1.0, median)[:, None, None]
    negative = np.clip(-vals[:, 0], 0.0, None) / np.where(degenerate, 1.0, median)  # rounding below 0
    out += negative[:, None, None] * np.eye(3)
    out[degenerate] = np.eye(3)
    if min_median is not None:
        out[median < min_median] = min_median * np.eye(3)
    return out


def inverse_sym3(C: np.ndarray, max_condition: float = 1e10) -> tuple[np.ndarray, np.ndarray]:
    """Inverses of (N,3,3) symmetric matrices by the adjugate; the Moore-Penrose
    pseudo-inverse where a matrix is singular or nearly so: det <= 0, or a Frobenius
    condition number ||C|| ||C^-1|| above `max_condition`.

    Returns (inverses (N,3,3), singular mask (N,))."""
    a00, a01, a02 = C[:, 0, 0], C[:, 0, 1], C[:, 0, 2]
    a11, a12, a22 = C[:, 1, 1], C[:, 1, 2], C[:, 2, 2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    norm_c = np.sqrt(a00 * a00 + a11 * a11 + a22 * a22 + 2 * (a01 * a01 + a02 * a02 + a12 * a12))
    norm_adj = np.sqrt(c00 * c00 + c11 * c11 + c22 * c22 + 2 * (c01 * c01 + c02 * c02 + c12 * c12))
    with np.errstate(invalid="ignore", over="ignore"):
        singular = ~((det > 0) & (norm_c * norm_adj < max_condition * det))
    inv_det = 1.0 / np.where(singular, 1.0, det)
    out = np.empty_like(C)
    out[:, 0, 0] = c00 * inv_det
    out[:, 1, 1] = c11 * inv_det
    out[:, 2, 2] = c22 * inv_det
    out[:, 0, 1] = out[:, 1, 0] = c01 * inv_det
    out[:, 0, 2] = out[:, 2, 0] = c02 * inv_det
    out[:, 1, 2] = out[:, 2, 1] = c12 * inv_det
    if singular.any():
        out[singular] = np.linalg.pinv(np.nan_to_num(C[singular]), hermitian=True)
    return out, singular


def whitening_sym3(C: np.ndarray, max_condition: float = 1e10) -> tuple[np.ndarray, np.ndarray]:
    """Matrices G (N,3,3) with G^T G = C^-1 for (N,3,3) symmetric positive definite C: the
    inverse of C's Cholesky factor, in closed form. Where C is singular or nearly so (a
    non-positive pivot, or a pivot ratio beyond sqrt(max_condition)), G^T G is the
    Moore-Penrose pseudo-inverse instead. Residuals whitened as G r give the Mahalanobis
    cost |G r|^2 = r^T C^-1 r.

    Returns (G, singular mask)."""
    n = len(C)
    b00, b11, b22 = C[:, 0, 0], C[:, 1, 1], C[:, 2, 2]
    b10, b20, b21 = C[:, 1, 0], C[:, 2, 0], C[:, 2, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        c00 = np.sqrt(b00)
        c10 = b10 / c00
        c20 = b20 / c00
        d11 = b11 - c10 * c10
        c11 = np.sqrt(d11)
        c21 = (b21 - c20 * c10) / c11
        d22 = b22 - c20 * c20 - c21 * c21
        c22 = np.sqrt(d22)
        big = np.maximum(np.maximum(b00, b11), b22)
        floor = big / max_condition
        singular = ~((b00 > floor) & (d11 > floor) & (d22 > floor))
        g00, g11, g22 = 1.0 / c00, 1.0 / c11, 1.0 / c22
        g10 = -c10 * g00 * g11
        g21 = -c21 * g11 * g22
        g20 = -(c20 * g00 + c21 * g10) * g22
    G = np.zeros((n, 3, 3))
    G[:, 0, 0], G[:, 1, 1], G[:, 2, 2] = g00, g11, g22
    G[:, 1, 0], G[:, 2, 1], G[:, 2, 0] = g10, g21, g20
    if singular.any():
        vals, vecs = np.linalg.eigh(np.nan_to_num(C[singular]))
        tol = np.maximum(vals.max(axis=1, keepdims=True), 0.0) / max_condition
        inv_sqrt = np.where(vals > tol, 1.0 / np.sqrt(np.where(vals > tol, vals, 1.0)), 0.0)
        G[singular] = inv_sqrt[:, :, None] * vecs.transpose(0, 2, 1)
    return G, singular
