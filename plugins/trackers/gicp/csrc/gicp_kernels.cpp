// Compiled kernels of the G-ICP tracker (plugins/trackers/gicp.py), behind a C ABI for ctypes.
//
// slk_grid_knn_covariances: k-NN covariances of a frame's points back-projected on a pixel grid.
//   Each point's k nearest neighbours are searched ring by ring in a (2h+1)^2 window of the grid
//   around it, stopping as soon as no point outside the rings searched can be closer than the
//   k-th found (a bound on how far in the image a 3D ball of that radius projects). Points it
//   cannot prove (flagged) take every point as a candidate: the whole is exact k-NN, ties at the
//   k-th distance going to the lower index as in the numpy reference.
// slk_grid_build / slk_grid_nearest: the nearest target mean within the correspondence distance,
//   by a uniform grid of cells over the means (exactly the nearest by float32 distance, ties to
//   the lower index, as pykdtree).
// slk_regularize_ellipse: the ellipse regularisation of covariances (eigenvalues by the
//   trigonometric formula; the rare rows the reference treats otherwise are left to it).
// slk_gicp_linearize / slk_gicp_cost: the normal equations of one Levenberg-Marquardt step and
//   the cost of a trial pose with the same correspondences and weights.
//
// The numpy code in slamkit/gaussian_geometry.py and plugins/trackers/gicp.py is the reference;
// tests/plugins/test_gicp_kernels.py checks that both agree.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

#include "slk_thread_pool.h"  // (slamkit/csrc) Pool, parallel_for

namespace {

// Sums are accumulated per block of this many points and the block sums added in block order, so
// results do not depend on the number of threads (the tracker is sensitive to rounding).
constexpr int kBlock = 1024;

// f(worker, lo, hi) on [0, n) split over up to nthreads threads, in chunks that are multiples of
// grain handed out by slamkit's persistent pool (slamkit/csrc/slk_thread_pool.h): no thread is
// started per call (a start and a join cost more than a short call's work on 2 cores), the
// caller works too and never waits for a worker that is not scheduled, and the workers run at
// the caller's priority. About four chunks a thread, so that a descheduled worker holds up little.
template <class F>
void parallel_ranges(int n, int nthreads, F f, int grain = 1) {
  nthreads = std::max(1, std::min(nthreads, (n + grain - 1) / grain));
  if (nthreads == 1) {
    f(0, 0, n);
    return;
  }
  const int64_t per_chunk = ((n + 4 * nthreads - 1) / (4 * nthreads) + grain - 1) / grain * grain;
  parallel_for(nthreads, n, per_chunk, [&](int64_t lo, int64_t hi, int worker) { f(worker, int(lo), int(hi)); });
}

// Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations: a = V diag(w) V^T.
void jacobi_eigh3(const double a_in[9], double w[3], double v[9]) {
  double a[9];
  std::copy(a_in, a_in + 9, a);
  for (int i = 0; i < 9; ++i) v[i] = (i % 4 == 0) ? 1.0 : 0.0;
  for (int sweep = 0; sweep < 50; ++sweep) {
    const double off = a[1] * a[1] + a[2] * a[2] + a[5] * a[5];
    if (off <= 1e-300) break;
    for (int p = 0; p < 2; ++p) {
      for (int q = p + 1; q < 3; ++q) {
        const double apq = a[3 * p + q];
        if (apq == 0.0) continue;
        const double theta = (a[3 * q + q] - a[3 * p + p]) / (2.0 * apq);
        const double t = (theta >= 0 ? 1.0 : -1.0) / (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
        const double c = 1.0 / std::sqrt(t * t + 1.0), s = t * c;
        for (int k = 0; k < 3; ++k) {  // a <- a J (columns p, q)
          const double akp = a[3 * k + p], akq = a[3 * k + q];
          a[3 * k + p] = c * akp - s * akq;
          a[3 * k + q] = s * akp + c * akq;
        }
        for (int k = 0; k < 3; ++k) {  // a <- J^T a (rows p, q)
          const double apk = a[3 * p + k], aqk = a[3 * q + k];
          a[3 * p + k] = c * apk - s * aqk;
          a[3 * q + k] = s * apk + c * aqk;
        }
        for (int k = 0; k < 3; ++k) {
          const double vkp = v[3 * k + p], vkq = v[3 * k + q];
          v[3 * k + p] = c * vkp - s * vkq;
          v[3 * k + q] = s * vkp + c * vkq;
        }
      }
    }
  }
  w[0] = a[0];
  w[1] = a[4];
  w[2] = a[8];
}

// W = C^-1 for a symmetric 3x3 C, stored as (w00, w01, w02, w11, w12, w22). The pivots of the
// Cholesky factorisation decide, as in slamkit.gaussian_geometry.whitening_sym3, whether C is
// treated as singular; then W is the Moore-Penrose pseudo-inverse. Returns true when singular.
bool inverse_sym3(const double c[9], double max_condition, double W[6]) {
  const double b00 = c[0], b11 = c[4], b22 = c[8], b10 = c[3], b20 = c[6], b21 = c[7];
  const double c00 = std::sqrt(b00);
  const double c10 = b10 / c00, c20 = b20 / c00;
  const double d11 = b11 - c10 * c10;
  const double c11 = std::sqrt(d11);
  const double c21 = (b21 - c20 * c10) / c11;
  const double d22 = b22 - c20 * c20 - c21 * c21;
  const double floor = std::max(std::max(b00, b11), b22) / max_condition;
  if (b00 > floor && d11 > floor && d22 > floor) {
    const double c22 = std::sqrt(d22);
    const double g00 = 1.0 / c00, g11 = 1.0 / c11, g22 = 1.0 / c22;
    const double g10 = -c10 * g00 * g11, g21 = -c21 * g11 * g22, g20 = -(c20 * g00 + c21 * g10) * g22;
    // W = G^T G with G lower triangular (rows: (g00), (g10 g11), (g20 g21 g22)).
    W[0] = g00 * g00 + g10 * g10 + g20 * g20;
    W[1] = g10 * g11 + g20 * g21;
    W[2] = g20 * g22;
    W[3] = g11 * g11 + g21 * g21;
    W[4] = g21 * g22;
    W[5] = g22 * g22;
    return false;
  }
  double a[9], w[3], v[9];
  for (int i = 0; i < 9; ++i) a[i] = std::isfinite(c[i]) ? c[i] : 0.0;
  jacobi_eigh3(a, w, v);
  const double tol = std::max(std::max(std::max(w[0], w[1]), w[2]), 0.0) / max_condition;
  double inv[3];
  for (int i = 0; i < 3; ++i) inv[i] = w[i] > tol ? 1.0 / w[i] : 0.0;
  const int idx[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
  for (int e = 0; e < 6; ++e) {
    const int r = idx[e][0], s = idx[e][1];
    W[e] = v[3 * r] * inv[0] * v[3 * s] + v[3 * r + 1] * inv[1] * v[3 * s + 1] + v[3 * r + 2] * inv[2] * v[3 * s + 2];
  }
  return true;
}

// Adds one correspondence's terms to A (H upper triangle (21), g (6), cost, singular count):
// s: the source row (p, C_s), u: the target row (mu, C_t). Writes q = R^T (mu - t) and W.
void add_correspondence(const double* s, const double* u, const double* R, const double* t,
                               double max_condition, double* A, double q[3], double W[6]) {
    const double d0 = u[0] - t[0], d1 = u[1] - t[1], d2 = u[2] - t[2];
        for (int a = 0; a < 3; ++a) q[a] = R[a] * d0 + R[3 + a] * d1 + R[6 + a] * d2;  // R^T d
    // C = R^T C_t R + C_s
    double CR[9], C[9];
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) CR[3 * a + b] = u[3 + 3 * a] * R[b] + u[3 + 3 * a + 1] * R[3 + b] + u[3 + 3 * a + 2] * R[6 + b];
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) C[3 * a + b] = R[a] * CR[b] + R[3 + a] * CR[3 + b] + R[6 + a] * CR[6 + b] + s[3 + 3 * a + b];
        A[28] += inverse_sym3(C, max_condition, W) ? 1.0 : 0.0;
    const double px = s[0], py = s[1], pz = s[2];
    const double r0 = q[0] - px, r1 = q[1] - py, r2 = q[2] - pz;
    const double w00 = W[0], w01 = W[1], w02 = W[2], w11 = W[3], w12 = W[4], w22 = W[5];
    const double Wr0 = w00 * r0 + w01 * r1 + w02 * r2, Wr1 = w01 * r0 + w11 * r1 + w12 * r2,
                 Wr2 = w02 * r0 + w12 * r1 + w22 * r2;
    // J = [S, -I], S = [p]x; J^T W J = [[S^T W S, -S^T W], [-W S, W]], J^T W r = [S^T W r, -W r].
    const double S[9] = {0, -pz, py, pz, 0, -px, -py, px, 0};
    const double Wm[9] = {w00, w01, w02, w01, w11, w12, w02, w12, w22};
    // Products with S's zero diagonal are left out (exactly: they only add zeros).
    double WS[9];
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) {
        const int k0 = b == 0 ? 1 : 0, k1 = b == 2 ? 1 : 2;  // the two k != b
        WS[3 * a + b] = Wm[3 * a + k0] * S[3 * k0 + b] + Wm[3 * a + k1] * S[3 * k1 + b];
      }
    double J[6][6];
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) {
        const int k0 = a == 0 ? 1 : 0, k1 = a == 2 ? 1 : 2;  // the two k != a
        J[a][b] = S[3 * k0 + a] * WS[3 * k0 + b] + S[3 * k1 + a] * WS[3 * k1 + b];  // S^T W S
        J[a][3 + b] = -WS[3 * b + a];                                                // -(W S)^T = -S^T W
        J[3 + a][3 + b] = Wm[3 * a + b];
      }
    int e = 0;
    for (int a = 0; a < 6; ++a)
      for (int b = a; b < 6; ++b) A[e++] += J[a][b];
    A[21] += S[3] * Wr1 + S[6] * Wr2;
    A[22] += S[1] * Wr0 + S[7] * Wr2;
    A[23] += S[2] * Wr0 + S[5] * Wr1;
    A[24] -= Wr0, A[25] -= Wr1, A[26] -= Wr2;
    A[27] += r0 * Wr0 + r1 * Wr1 + r2 * Wr2;}


// ---------------------------------------------------------------------------------------------
// A uniform grid over the target means for the per-iteration nearest-neighbour search: the means
// sorted by cell, and each cell's first mean in that order (cells x-major, z fastest, over the
// means' bounding box).
// A query scans the cells of the box [q - r, q + r] (r: the search radius, or the hint's distance
// when smaller), skipping those farther from q than the best mean found so far. Squared distances are
// summed in float32 dimension by dimension, as pykdtree does for float32 data, and an equal
// distance goes to the lower index: the result is the nearest mean by (float32 distance, index)
// whatever the cell size. A hint (the previous iteration's match) starts the search with a small
// radius.

inline float dist2(const float* a, const float* b) {
  const float dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
  float d = dx * dx;
  d += dy * dy;
  d += dz * dz;
  return d;
}

// A (float32 squared distance, index) pair as one integer ordered as the pairs are (the bits of
// a float >= 0 are ordered as its value): the nearest by distance, ties to the lower index, is
// the minimum.
inline uint64_t pack(float d, uint32_t index) {
  uint32_t bits;
  std::memcpy(&bits, &d, 4);
  return (uint64_t(bits) << 32) | index;
}
inline float distance_of(uint64_t key) {
  const uint32_t bits = uint32_t(key >> 32);
  float d;
  std::memcpy(&d, &bits, 4);
  return d;
}
inline uint32_t index_of(uint64_t key) { return uint32_t(key); }


// At most this many cells (8 MB of offsets): a bigger box gets coarser cells.
constexpr int64_t kMaxCells = int64_t(1) << 21;

struct CellGrid {
  double origin[3] = {0, 0, 0};  // the corner of cell (0, 0, 0), metres
  double inv_h = 1.0, h = 1.0;
  int64_t extent[3] = {1, 1, 1};  // cells per axis (the finite means' bounding box)
  std::vector<float> means;       // (n,3) as given
  // The means by cell (x-major, z fastest), then index: coordinates and index, one array each
  // (the scan over a run of means vectorises).
  std::vector<float> xs, ys, zs;
  std::vector<uint32_t> order;
  std::vector<int32_t> first;     // per cell: its first point; one more entry: the end
  int n = 0;

  // The cell coordinate along axis a of coordinate v (as a double, before clamping).
  double cell_coord(double v, int a) const { return std::floor((v - origin[a]) * inv_h); }
  int64_t cell_id(int64_t a, int64_t b, int64_t c) const { return (a * extent[1] + b) * extent[2] + c; }

  void build(int count, const float* xyz, double cell_size) {
    n = count;
    means.assign(xyz, xyz + 3 * size_t(n));
    auto finite = [&](int i) {
      const float* p = xyz + 3 * size_t(i);
      return std::isfinite(p[0]) && std::isfinite(p[1]) && std::isfinite(p[2]);
    };
    double lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};
    bool any = false;
    for (int i = 0; i < n; ++i) {
      if (!finite(i)) continue;  // never within a finite distance: left out
      for (int a = 0; a < 3; ++a) {
        const double v = xyz[3 * size_t(i) + a];
        lo[a] = any ? std::min(lo[a], v) : v;
        hi[a] = any ? std::max(hi[a], v) : v;
      }
      any = true;
    }
    for (int a = 0; a < 3; ++a) origin[a] = lo[a];
    for (h = cell_size;; h *= 1.25) {  // coarser cells while the box holds too many
      inv_h = 1.0 / h;
      double cells = 1.0;
      for (int a = 0; a < 3; ++a) cells *= cell_coord(hi[a], a) + 1.0;
      if (cells <= double(kMaxCells)) break;
    }
    for (int a = 0; a < 3; ++a) extent[a] = int64_t(cell_coord(hi[a], a)) + 1;
    std::vector<int32_t> cell(n, -1);
    first.assign(size_t(extent[0] * extent[1] * extent[2]) + 1, 0);
    for (int i = 0; i < n; ++i) {
      if (!finite(i)) continue;
      int64_t c[3];
      for (int a = 0; a < 3; ++a)
        c[a] = std::min<int64_t>(extent[a] - 1, std::max<int64_t>(0, int64_t(cell_coord(xyz[3 * size_t(i) + a], a))));
      cell[i] = int32_t(cell_id(c[0], c[1], c[2]));
      first[cell[i] + 1]++;
    }
    for (size_t c = 1; c < first.size(); ++c) first[c] += first[c - 1];
    const size_t kept = size_t(first.back());
    xs.resize(kept), ys.resize(kept), zs.resize(kept), order.resize(kept);
    std::vector<int32_t> fill(first.begin(), first.end() - 1);
    for (int i = 0; i < n; ++i) {  // in index order: each cell's run ascending by index
      if (cell[i] < 0) continue;
      const int32_t at = fill[cell[i]]++;
      xs[at] = xyz[3 * size_t(i)], ys[at] = xyz[3 * size_t(i) + 1], zs[at] = xyz[3 * size_t(i) + 2];
      order[at] = uint32_t(i);
    }
  }

  // The best of `best` and the means at [lo, hi) in cell order (as dist2 and pack).
  uint64_t scan(const float* q, int32_t lo, int32_t hi, uint64_t best) const {
    const float qx = q[0], qy = q[1], qz = q[2];
    for (int32_t k = lo; k < hi; ++k) {
      const float dx = qx - xs[k], dy = qy - ys[k], dz = qz - zs[k];
      float d = dx * dx;
      d += dy * dy;
      d += dz * dz;
      best = std::min(best, pack(d, order[k]));
    }
    return best;
  }

  // The nearest mean to q by (float32 squared distance, index) better than `best`, a
  // (distance, index) key (see pack); returns the better key.
  uint64_t nearest(const float* q, uint64_t best) const {
    if (n == 0 || !(std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]))) return best;
    // A mean whose float32 squared distance is <= d is within this of q along each axis
    // (rounding makes the float32 distance at most a few ulps smaller than the true one).
    const double reach = std::sqrt(double(distance_of(best))) * (1.0 + 1e-6);
    int64_t lo[3], hi[3];
    double u[3];  // q in cell units
    for (int a = 0; a < 3; ++a) {
      u[a] = (double(q[a]) - origin[a]) * inv_h;
      const double l = cell_coord(double(q[a]) - reach, a), r = cell_coord(double(q[a]) + reach, a);
      if (r < 0 || l >= double(extent[a])) return best;
      lo[a] = l < 0 ? 0 : int64_t(l);
      hi[a] = r >= double(extent[a]) ? extent[a] - 1 : int64_t(r);
    }
    // Squared distance (m^2) from q to cell c along axis a, less a margin for rounding, and
    // times a factor below 1: a float32 distance exceeds the true one by far less.
    auto gap2 = [&](int a, int64_t c) {
      const double g = std::max(double(c) - u[a], u[a] - double(c + 1)) - 1e-6;
      return g > 0 ? g * g * (h * h * (1.0 - 1e-5)) : 0.0;
    };
    for (int64_t a = lo[0]; a <= hi[0]; ++a) {
      const double da = gap2(0, a);
      if (da > distance_of(best)) continue;
      for (int64_t b = lo[1]; b <= hi[1]; ++b) {
        const double dab = da + gap2(1, b);
        if (dab > distance_of(best)) continue;
        // the cells (a, b, c) within reach are one run of points
        int64_t c0 = lo[2], c1 = hi[2];
        while (c0 <= c1 && dab + gap2(2, c0) > distance_of(best)) ++c0;
        while (c1 >= c0 && dab + gap2(2, c1) > distance_of(best)) --c1;
        if (c0 > c1) continue;
        best = scan(q, first[cell_id(a, b, c0)], first[cell_id(a, b, c1) + 1], best);
      }
    }
    return best;
  }
};
}  // namespace

extern "C" {

// A grid over n means (float32 (n,3), metres) with cells of cell_size metres (or coarser for a
// box too big for 2^21 cells an axis); free it with slk_grid_free.
void* slk_grid_build(int n, const float* points, double cell_size) {
  auto* grid = new CellGrid();
  grid->build(n, points, cell_size);
  return grid;
}

void slk_grid_free(void* grid) { delete static_cast<CellGrid*>(grid); }

// For each query (float32 (m,3)), the nearest mean within squared distance max_d2 (inclusive
// bound as `<=`): index in out_idx (n = grid size where none) and squared distance in out_d2
// (float32). hint: (m) a candidate index per query (>= n: none), e.g. the last match; where
// none, the previous query's match is tried first (a neighbour's, for queries in image order).
void slk_grid_nearest(const void* handle, int m, const float* queries, float max_d2, const uint32_t* hint,
                      uint32_t* out_idx, float* out_d2, int nthreads) {
  const CellGrid& grid = *static_cast<const CellGrid*>(handle);
  const int n = grid.n;
  parallel_ranges(m, nthreads, [&](int, int lo, int hi) {
    for (int j = lo; j < hi; ++j) {
      const float* q = queries + 3 * size_t(j);
      // at the bound with an index above any: a mean exactly at the bound is accepted
      uint64_t best = pack(max_d2, ~uint32_t(0));
      // the hint, else the previous query's match (queries in image order: a neighbour's)
      uint32_t start = hint != nullptr ? hint[j] : uint32_t(n);
      if (start >= uint32_t(n) && j > lo) start = out_idx[j - 1];
      if (start < uint32_t(n)) best = std::min(best, pack(dist2(q, &grid.means[3 * size_t(start)]), start));
      best = grid.nearest(q, best);
      const bool found = index_of(best) < uint32_t(n);
      out_idx[j] = found ? index_of(best) : uint32_t(n);
      out_d2[j] = found ? distance_of(best) : std::numeric_limits<float>::infinity();
    }
  });
}

int slk_abi_version() { return 6; }

// points: (n,3) float32, camera frame, metres. cell: (n) the grid cell (row * gw + col) of each
// point; grid: (gh*gw) the point in each cell or -1. fx, fy: focal lengths in pixels; stride:
// pixels between grid cells; half: the window's half-width in cells. Writes cov (n,9) float64
// and exact (n): 1 where the window proved the neighbours, 0 where all n points were searched.
void slk_grid_knn_covariances(int n, const float* points, const int32_t* cell, const int32_t* grid, int gh, int gw,
                              int k, int half, double fx, double fy, double stride, double* cov, uint8_t* exact,
                              int nthreads) {
  parallel_ranges(n, nthreads, [&](int, int lo, int hi) {
    std::vector<double> best_d(k + 1);
    std::vector<int> best_i(k + 1);
    for (int i = lo; i < hi; ++i) {
      const float* p = points + 3 * i;
      const double x = p[0], y = p[1], z = p[2];
      const int row = cell[i] / gw, col = cell[i] % gw;
      int found = 0;
      auto consider = [&](int j) {
        const float* q = points + 3 * j;
        const double dx = double(q[0]) - x, dy = double(q[1]) - y, dz = double(q[2]) - z;
        const double d = dx * dx + dy * dy + dz * dz;
        // Order by (distance, index), as slamkit.gaussian_geometry.knn_covariances does.
        if (found == k && (d > best_d[k - 1] || (d == best_d[k - 1] && j > best_i[k - 1]))) return;
        int pos = found < k ? found++ : k - 1;  // insertion into the sorted best list
        while (pos > 0 && (best_d[pos - 1] > d || (best_d[pos - 1] == d && best_i[pos - 1] > j))) {
          best_d[pos] = best_d[pos - 1];
          best_i[pos] = best_i[pos - 1];
          --pos;
        }
        best_d[pos] = d;
        best_i[pos] = j;
      };
      auto visit = [&](int r, int c) {
        if (r < 0 || r >= gh || c < 0 || c >= gw) return;
        const int j = grid[r * gw + c];
        if (j >= 0) consider(j);
      };
      // A point within distance rad of p projects at most fx rad (z + |x|) / ((z - rad) z) pixels
      // from p in u (|x_q/z_q - x_p/z_p| bounded for |q - p| <= rad), likewise in v; once that
      // is inside the rings searched, no point outside them can be among the k nearest.
      auto proven = [&](int rings) {
        if (found < k) return false;
        const double rad = std::sqrt(best_d[k - 1]);
        const double reach = (rings + 1) * stride - 1e-2;  // float32 points move u, v by ~1e-4 px
        return z > rad && fx * rad * (z + std::fabs(x)) < reach * (z - rad) * z &&
               fy * rad * (z + std::fabs(y)) < reach * (z - rad) * z;
      };
      bool ok = false;
      for (int ring = 0; ring <= half && !ok; ++ring) {  // rings of cells, nearest first
        if (ring == 0) {
          visit(row, col);
        } else {
          for (int c = col - ring; c <= col + ring; ++c) visit(row - ring, c), visit(row + ring, c);
          for (int r = row - ring + 1; r <= row + ring - 1; ++r) visit(r, col - ring), visit(r, col + ring);
        }
        ok = proven(ring);
      }
      exact[i] = ok ? 1 : 0;
      if (!ok) {  // every point, then (a depth edge or a hole: rare)
        found = 0;
        for (int j = 0; j < n; ++j) consider(j);
      }
      double* out = cov + 9 * i;
      double m[3] = {0, 0, 0}, s[6] = {0, 0, 0, 0, 0, 0};
      for (int a = 0; a < k; ++a) {
        const float* q = points + 3 * best_i[a];
        const double g0 = double(q[0]) - x, g1 = double(q[1]) - y, g2 = double(q[2]) - z;
        m[0] += g0, m[1] += g1, m[2] += g2;
        s[0] += g0 * g0, s[1] += g0 * g1, s[2] += g0 * g2, s[3] += g1 * g1, s[4] += g1 * g2, s[5] += g2 * g2;
      }
      for (double& v : m) v /= k;
      const double c00 = s[0] / k - m[0] * m[0], c01 = s[1] / k - m[0] * m[1], c02 = s[2] / k - m[0] * m[2];
      const double c11 = s[3] / k - m[1] * m[1], c12 = s[4] / k - m[1] * m[2], c22 = s[5] / k - m[2] * m[2];
      out[0] = c00, out[1] = c01, out[2] = c02;
      out[3] = c01, out[4] = c11, out[5] = c12;
      out[6] = c02, out[7] = c12, out[8] = c22;
    }
  });
}

// Ellipse regularisation of n covariances (cov: (n,9) float64, m^2), as
// slamkit.geometry.gaussians.regularize (the reference, with the same operations in the same
// order; libm's acos / cos / pow may round differently from numpy's by an ulp): each C becomes
// C / l2 + max(-l3, 0) / l2 I with l3 <= l2 <= l1 its eigenvalues (trigonometric formula on C
// scaled by its largest entry), I where l2 <= 1e-12 l1, and min_median I where l2 < min_median
// (NaN: never). Rows whose eigenvalues the reference takes from its accurate path (a nearly
// repeated pair) or that are not finite are flagged in redo (1) and left for the caller.
void slk_regularize_ellipse(int n, const double* cov, double min_median, double* out, uint8_t* redo, int nthreads) {
  const double third_turn = 2.0 * 3.141592653589793 / 3.0;
  parallel_ranges(n, nthreads, [&](int, int lo, int hi) {
    for (int i = lo; i < hi; ++i) {
      const double* A = cov + 9 * size_t(i);
      double* C = out + 9 * size_t(i);
      double scale = 0.0;
      bool finite = true;
      for (int e = 0; e < 9; ++e) scale = std::max(scale, std::fabs(A[e])), finite = finite && std::isfinite(A[e]);
      if (!finite) {
        redo[i] = 1;
        continue;
      }
      if (!(scale > 0)) scale = 1.0;
      const double a00 = A[0] / scale, a11 = A[4] / scale, a22 = A[8] / scale;
      const double a01 = A[1] / scale, a02 = A[2] / scale, a12 = A[5] / scale;
      const double q = (a00 + a11 + a22) / 3.0;
      const double b00 = a00 - q, b11 = a11 - q, b22 = a22 - q;
      const double p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0;
      const double p = std::sqrt(p2);
      const double safe_p = p > 0 ? p : 1.0;
      const double det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02);
      const double r = std::min(1.0, std::max(-1.0, det / (2.0 * std::pow(safe_p, 3.0))));
      const double phi = std::acos(r) / 3.0;
      const double l_max = q + 2.0 * p * std::cos(phi);
      const double l_min = q + 2.0 * p * std::cos(phi + third_turn);
      const double l_mid = 3.0 * q - l_max - l_min;
      const double gap = std::min(l_mid - l_min, l_max - l_mid);
      const double top = std::max(std::fabs(l_min), std::max(std::fabs(l_mid), std::fabs(l_max)));
      const double v0 = l_min * scale, v1 = l_mid * scale, v2 = l_max * scale;
      if (!(gap >= 1e-4 * top) || !std::isfinite(v0) || !std::isfinite(v1) || !std::isfinite(v2)) {
        redo[i] = 1;
        continue;
      }
      redo[i] = 0;
      const bool degenerate = !(v1 > 1e-12 * std::max(v2, 1e-300));
      const double median = degenerate ? 1.0 : v1;
      const double negative = std::max(-v0, 0.0) / median;
      for (int e = 0; e < 9; ++e) C[e] = A[e] / median + (e % 4 == 0 ? negative : 0.0);
      if (degenerate)
        for (int e = 0; e < 9; ++e) C[e] = e % 4 == 0 ? 1.0 : 0.0;
      if (v1 < min_median)
        for (int e = 0; e < 9; ++e) C[e] = e % 4 == 0 ? min_median : 0.0;
    }
  });
}

// One Gauss-Newton linearisation of the G-ICP cost at pose (R, t) (camera-to-world, R row-major).
// src: (n,12) float64 rows (p, C_s row-major) in the camera frame; tgt: (N,12) rows (mu, C_t) in
// the world frame; nn: (n) index of each source point's target, >= N where none. With
// r_i = R^T (mu - t) - p and W_i = (R^T C_t R + C_s)^-1, accumulates H = sum J^T W J,
// g = sum J^T W r, cost = sum r^T W r for J = dr/dxi = [[p]x, -I] (xi = (omega, v), T <- T exp(xi)).
// Saves, per matched point in source order, its source row (sel), q = R^T (mu - t) and W for
// slk_gicp_cost. out_stats: (cost, matched, singular). Returns the number matched.
int slk_gicp_linearize(int n, const double* src, int n_target, const double* tgt, const uint32_t* nn,
                       const double* R, const double* t, double max_condition, double* H, double* g,
                       int32_t* sel, double* q_out, double* W_out, double* out_stats, int nthreads) {
  // Matched points are packed in source order: a prefix count gives each thread its slots.
  std::vector<int32_t> offsets(n + 1, 0);
  for (int i = 0; i < n; ++i) offsets[i + 1] = offsets[i] + (nn[i] < uint32_t(n_target) ? 1 : 0);
  const int m = offsets[n];
  const int nblocks = (n + kBlock - 1) / kBlock;
  std::vector<double> acc(size_t(nblocks) * 29, 0.0);  // per block: H (21 upper), g (6), cost, singular
  parallel_ranges(n, nthreads, [&](int, int lo, int hi) {  // lo, hi: multiples of kBlock (or n): one writer per block
    for (int i = lo; i < hi; ++i) {
      if (nn[i] >= uint32_t(n_target)) continue;
      const int slot = offsets[i];
      double* A = acc.data() + size_t(i / kBlock) * 29;
      add_correspondence(src + 12 * size_t(i), tgt + 12 * size_t(nn[i]), R, t, max_condition, A,
                         q_out + 3 * size_t(slot), W_out + 6 * size_t(slot));
      sel[slot] = i;
    }
  }, kBlock);
  double total[29] = {0};
  for (int block = 0; block < nblocks; ++block)
    for (int e = 0; e < 29; ++e) total[e] += acc[size_t(block) * 29 + e];
  int e = 0;
  for (int a = 0; a < 6; ++a)
    for (int b = a; b < 6; ++b) H[6 * a + b] = H[6 * b + a] = total[e++];
  for (int a = 0; a < 6; ++a) g[a] = total[21 + a];
  out_stats[0] = total[27];
  out_stats[1] = m;
  out_stats[2] = total[28];
  return m;
}

// The cost sum r'^T W r' of the m matched points saved by slk_gicp_linearize at a trial pose
// (Rn, tn): r' = q - b - A p with A = R^T Rn and b = R^T (tn - t) (row-major A).
double slk_gicp_cost(int m, const double* src, const int32_t* sel, const double* q, const double* W, const double* A,
                     const double* b, int nthreads) {
  const int nblocks = (m + kBlock - 1) / kBlock;
  std::vector<double> acc(nblocks, 0.0);
  parallel_ranges(nblocks, nthreads, [&](int, int block_lo, int block_hi) {
    for (int block = block_lo; block < block_hi; ++block) {
      double sum = 0.0;
      for (int k = block * kBlock; k < std::min(m, (block + 1) * kBlock); ++k) {
        const double* p = src + 12 * size_t(sel[k]);
        const double* qk = q + 3 * size_t(k);
        const double* w = W + 6 * size_t(k);
        double r[3];
        for (int a = 0; a < 3; ++a) r[a] = qk[a] - b[a] - (A[3 * a] * p[0] + A[3 * a + 1] * p[1] + A[3 * a + 2] * p[2]);
        sum += w[0] * r[0] * r[0] + w[3] * r[1] * r[1] + w[5] * r[2] * r[2] +
               2.0 * (w[1] * r[0] * r[1] + w[2] * r[0] * r[2] + w[4] * r[1] * r[2]);
      }
      acc[block] = sum;
    }
  });
  double total = 0.0;
  for (double v : acc) total += v;
  return total;
}

}  // extern "C"
