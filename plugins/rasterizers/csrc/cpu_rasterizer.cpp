// slamkit CPU rasteriser: tile-based differentiable 3D Gaussian Splatting, forward and backward.
//
// Plain C++17 with a C ABI (loaded with ctypes by slamkit_plugins/rasterizers/cpu_rasterizer.py):
// no torch headers, so it builds in seconds with any C++17 compiler and does not depend on the
// torch version (GCC >= 9 or Clang; vector extensions). Threads: a persistent pool, work handed
// out dynamically in chunks; results are independent of the thread count (every sum has a
// fixed order).
//
// Conventions: exactly those of slamkit.rendering.Rasterizer and the `torch` backend
// (plugins/rasterizers/torch_rasterizer.py), which is the reference:
//   - p = R m + t; culled when p_z <= 0.01 or opacity <= 1/255 (float32 compare);
//   - u = fx x / z + cx, v = fy y / z + cy; J with x/z, y/z clamped to the image extended by
//     15 % (+0.5 px) on each side; 2D covariance J R Sigma R^T J^T + 0.3 I; conic = its inverse;
//   - a Gaussian covers, row by row, exactly the columns the torch backend's closed-form
//     interval gives (the same float32 operations in the same order: compiled with
//     -ffp-contract=off and without -ffast-math so they are reproduced bit for bit);
//   - log alpha = log o - q / 2, alpha = min(0.99, exp(log alpha));
//   - per pixel, front to back by camera z (ties by index); stop at the first Gaussian that
//     would bring the transmittance below 1e-4;
//   - colour = sum w c + (1 - sum w) bg, depth = sum w z, alpha = sum w, w = alpha T (the
//     background's weight is computed as the final transmittance, equal to 1 - sum w).
// The projection (means, quats, scales -> 2D mean, conic) and its backward are computed in
// double precision, four Gaussians at a time (the same operations in the same order as for one,
// so the same bits); the pixel work in float32 (16 pixels per vector, slamkit/csrc/slk_vec16.h),
// the per-Gaussian gradient sums in double.
//
// Forward: project + cull (parallel over Gaussians) -> radix sort by depth -> binning into
// 16x16 tiles (each Gaussian is listed, in depth order, in the tiles its exact row intervals
// touch) -> per tile, 32 entries at a time: their row spans (16 rows at once), per tile row the
// entries covering it, then each row (16 pixels = one vector; without AVX-512, each 8-pixel
// half that a span meets) composited with its state in registers, the alphas of four entries
// computed at once; per-pixel early termination, per-row and per-tile early exit. Kept for the
// backward pass: the final transmittance and the last composited list position of every pixel,
// and (when a backward pass follows) every composited block's alphas (AlphaStore).
// Backward: per tile, the list walked back to front (the stored alphas; transmittance recovered
// by division, the suffix sum sum_{j>i} w_j v_j carried per pixel), per (tile, Gaussian) entry ten moments
// accumulated in registers and stored in that entry's own slot (no atomics); then per Gaussian
// the slots are reduced in a fixed order (deterministic) and the projection's analytic backward
// gives the gradients w.r.t. means, quaternions, scales, opacities and colours.

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <ctime>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <exception>
#include <memory>
#include <mutex>
#include <new>
#include <thread>
#include <type_traits>
#include <vector>

#include <unistd.h>

#include "slk_thread_pool.h"  // (slamkit/csrc) Pool, parallel_for
#include "slk_vec16.h"        // (slamkit/csrc) 16-lane vectors

namespace {

constexpr int ABI_VERSION = 5;
constexpr int TILE = 16;
constexpr int TILE_PIX = TILE * TILE;
constexpr double NEAR_PLANE = 0.01;
constexpr double EPS_2D = 0.3;
constexpr float ALPHA_MAX = 0.99f;
constexpr double T_MIN = 1e-4;
constexpr double JACOBIAN_MARGIN = 0.15;
constexpr int NUM_MOMENTS = 10;

// ------------------------------------------------------------------------------------------
// Threads and timing

struct Stamp {  // wall-clock and process CPU time, microseconds
  int64_t wall, cpu;
};

inline Stamp now_us() {
  Stamp s;
  s.wall = std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::steady_clock::now().time_since_epoch())
               .count();
  s.cpu = (int64_t)((double)std::clock() * 1e6 / CLOCKS_PER_SEC);
  return s;
}

// ------------------------------------------------------------------------------------------
// Camera and projection (double precision)

struct Camera {
  int W, H;
  double fx, fy, cx, cy;
  double R[9], t[3];
  double lim_x0, lim_x1, lim_y0, lim_y1;  // tx in [-lim_x0, lim_x1], ty in [-lim_y0, lim_y1]
};

Camera make_camera(const double* viewmat, const double* intr, int W, int H) {
  Camera c;
  c.W = W;
  c.H = H;
  c.fx = intr[0];
  c.fy = intr[1];
  c.cx = intr[2];
  c.cy = intr[3];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.R[3 * i + j] = viewmat[4 * i + j];
    c.t[i] = viewmat[4 * i + 3];
  }
  // as the torch backend: the values are float32 where it clamps (a python float on a float32
  // tensor), so round them the same way
  c.lim_x0 = (float)((JACOBIAN_MARGIN * W + c.cx + 0.5) / c.fx);
  c.lim_x1 = (float)((W * (1 + JACOBIAN_MARGIN) - c.cx - 0.5) / c.fx);
  c.lim_y0 = (float)((JACOBIAN_MARGIN * H + c.cy + 0.5) / c.fy);
  c.lim_y1 = (float)((H * (1 + JACOBIAN_MARGIN) - c.cy - 0.5) / c.fy);
  return c;
}

// The projection and its backward run on four Gaussians at once: d4, four doubles (GCC / Clang
// vector extensions: two SSE2 or one AVX register), with the same IEEE operations lane by lane
// as the scalar code they replaced, so the same bits. Masks (comparisons) are m4, lanes 0 or -1.
typedef double d4 __attribute__((vector_size(32)));
typedef int64_t m4 __attribute__((vector_size(32)));
constexpr int PROJECT_LANES = 4;

inline d4 d4_of(double x) { return d4{x, x, x, x}; }
inline d4 dselect(m4 mask, d4 a, d4 b) { return (d4)(((m4)a & mask) | ((m4)b & ~mask)); }
inline d4 vmin(d4 a, d4 b) { return dselect(b < a, b, a); }  // std::min's and std::max's choices, NaNs included
inline d4 vmax(d4 a, d4 b) { return dselect(a < b, b, a); }
inline d4 dsqrt(d4 x) {
  for (int k = 0; k < PROJECT_LANES; ++k) x[k] = std::sqrt(x[k]);
  return x;
}

// out[j] = column j of the rows idx[0..4) of a row-major float array `width` wide, as doubles
inline void gather(const float* rows, int width, const int64_t* idx, d4* out) {
  const float* r[PROJECT_LANES];
  for (int k = 0; k < PROJECT_LANES; ++k) r[k] = rows + width * idx[k];
  for (int j = 0; j < width; ++j) out[j] = d4{r[0][j], r[1][j], r[2][j], r[3][j]};
}

// Which of the four Gaussians idx[0..4) may cover a pixel (bit k for idx[k]): in front of the
// near plane and not surely off screen. The off-screen test is a bound on the extent that is cheap
// to compute (most Gaussians of a map are outside a given view; `project` costs ~10x this): the
// ellipse's half-extents are sqrt(level sxx) and sqrt(level syy), and sxx, syy <= the trace of
// J R S^2 R^T J^T + 0.3 <= smax^2 |J|_F^2 + 0.3 (J with the clamped tx, ty as in `project`), and
// level = 2 ln(255 o) <= 2 ln 255 (o <= 1: no logarithm per Gaussian); the bound is widened by
// 1 % and 2 px, far beyond rounding, so it never culls a Gaussian `project` would keep.
inline int maybe_visible(const Camera& cam, const int64_t* idx, const float* means, const float* scales) {
  static const double level_max = 2.0 * std::log(255.0);
  d4 m[3], smax;
  gather(means, 3, idx, m);
  for (int k = 0; k < PROJECT_LANES; ++k) {
    const float* sk = scales + 3 * idx[k];
    smax[k] = std::max(std::fabs((double)sk[0]), std::max(std::fabs((double)sk[1]), std::fabs((double)sk[2])));
  }
  const double* R = cam.R;
  d4 p[3];
  for (int i = 0; i < 3; ++i) p[i] = R[3 * i] * m[0] + R[3 * i + 1] * m[1] + R[3 * i + 2] * m[2] + cam.t[i];
  const d4 iz = 1.0 / p[2];
  const d4 tx = vmin(vmax(p[0] * iz, d4_of(-cam.lim_x0)), d4_of(cam.lim_x1));
  const d4 ty = vmin(vmax(p[1] * iz, d4_of(-cam.lim_y0)), d4_of(cam.lim_y1));
  const d4 j2 = (cam.fx * cam.fx * (1 + tx * tx) + cam.fy * cam.fy * (1 + ty * ty)) * iz * iz;
  const d4 r = 1.01 * dsqrt(level_max * (j2 * smax * smax + EPS_2D)) + 2.0;
  const d4 u = cam.fx * p[0] * iz + cam.cx, v = cam.fy * p[1] * iz + cam.cy;
  const m4 off = (u + r < 0.0) | (u - r > (double)(cam.W - 1)) | (v + r < 0.0) | (v - r > (double)(cam.H - 1));
  const m4 keep = (p[2] > NEAR_PLANE) & ~off;
  int bits = 0;
  for (int k = 0; k < PROJECT_LANES; ++k) bits |= (keep[k] != 0) << k;
  return bits;
}

struct Projection {  // everything the forward computes, kept to differentiate it
  d4 p[3], iz, txr, tyr, tx, ty;
  d4 qn[4], qnorm, Rq[9], s2[3];
  d4 M[6];  // J R (2x3)
  d4 A[6];  // M Rq (2x3): cov2d = A diag(s^2) A^T
  d4 sxx, sxy, syy, a, b, c, u, v;
};

inline void quat_to_rotmat(const d4* q, d4* R) {
  d4 w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z);
  R[1] = 2 * (x * y - w * z);
  R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);
  R[4] = 1 - 2 * (x * x + z * z);
  R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);
  R[7] = 2 * (y * z + w * x);
  R[8] = 1 - 2 * (x * x + y * y);
}

// m, q, s: a Gaussian's mean, quaternion (w, x, y, z) and scales, as doubles
void project(const Camera& cam, const d4* m, const d4* q, const d4* s, Projection& P) {
  const double* R = cam.R;
  for (int i = 0; i < 3; ++i) P.p[i] = R[3 * i] * m[0] + R[3 * i + 1] * m[1] + R[3 * i + 2] * m[2] + cam.t[i];
  d4 x = P.p[0], y = P.p[1], z = P.p[2];
  P.iz = 1.0 / z;
  P.u = cam.fx * x * P.iz + cam.cx;
  P.v = cam.fy * y * P.iz + cam.cy;
  P.txr = x * P.iz;
  P.tyr = y * P.iz;
  P.tx = vmin(vmax(P.txr, d4_of(-cam.lim_x0)), d4_of(cam.lim_x1));
  P.ty = vmin(vmax(P.tyr, d4_of(-cam.lim_y0)), d4_of(cam.lim_y1));
  d4 J00 = cam.fx * P.iz, J02 = -cam.fx * P.tx * P.iz;
  d4 J11 = cam.fy * P.iz, J12 = -cam.fy * P.ty * P.iz;
  for (int j = 0; j < 3; ++j) {
    P.M[j] = J00 * R[j] + J02 * R[6 + j];
    P.M[3 + j] = J11 * R[3 + j] + J12 * R[6 + j];
  }
  P.qnorm = dsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  for (int i = 0; i < 4; ++i) P.qn[i] = q[i] / P.qnorm;
  quat_to_rotmat(P.qn, P.Rq);
  for (int k = 0; k < 3; ++k) P.s2[k] = s[k] * s[k];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      P.A[3 * r + k] = P.M[3 * r] * P.Rq[k] + P.M[3 * r + 1] * P.Rq[3 + k] + P.M[3 * r + 2] * P.Rq[6 + k];
  d4 c00 = d4_of(0), c01 = d4_of(0), c11 = d4_of(0);
  for (int k = 0; k < 3; ++k) {
    c00 += P.A[k] * P.A[k] * P.s2[k];
    c01 += P.A[k] * P.A[3 + k] * P.s2[k];
    c11 += P.A[3 + k] * P.A[3 + k] * P.s2[k];
  }
  P.sxx = c00 + EPS_2D;
  P.syy = c11 + EPS_2D;
  P.sxy = c01;
  d4 inv_det = 1.0 / (P.sxx * P.syy - P.sxy * P.sxy);
  P.a = P.syy * inv_det;
  P.b = -P.sxy * inv_det;
  P.c = P.sxx * inv_det;
}

// Gradients of (u, v, conic a b c, z) -> means, quats, scales (gm, gq, gs; s the scales).
void project_backward(const Camera& cam, const Projection& P, const d4* s, d4 gu, d4 gv, d4 ga, d4 gb, d4 gc,
                      d4 gz_direct, d4* gm, d4* gq, d4* gs) {
  const d4 a = P.a, b = P.b, c = P.c;
  // conic = cov^-1: dL/dcov = -C G C (G the symmetric gradient w.r.t. the conic matrix)
  d4 g_sxx = -(a * a * ga + a * b * gb + b * b * gc);
  d4 g_syy = -(b * b * ga + b * c * gb + c * c * gc);
  d4 g_sxy = -(2 * a * b * ga + (a * c + b * b) * gb + 2 * b * c * gc);
  // cov2d = A S A^T, S = diag(s^2); Gcov = [[g_sxx, g_sxy/2], [g_sxy/2, g_syy]]
  const d4* A = P.A;
  d4 gA[6];
  for (int k = 0; k < 3; ++k) {
    // (Gcov A)_rk, then times 2 s_k^2
    d4 r0 = g_sxx * A[k] + 0.5 * g_sxy * A[3 + k];
    d4 r1 = 0.5 * g_sxy * A[k] + g_syy * A[3 + k];
    gA[k] = 2 * r0 * P.s2[k];
    gA[3 + k] = 2 * r1 * P.s2[k];
    d4 q = A[k] * A[k] * g_sxx + A[k] * A[3 + k] * g_sxy + A[3 + k] * A[3 + k] * g_syy;
    gs[k] = 2 * s[k] * q;
  }
  // A = M Rq: dL/dM = gA Rq^T, dL/dRq = M^T gA
  d4 gM[6], gR[9];
  for (int r = 0; r < 2; ++r)
    for (int j = 0; j < 3; ++j)
      gM[3 * r + j] = gA[3 * r] * P.Rq[3 * j] + gA[3 * r + 1] * P.Rq[3 * j + 1] + gA[3 * r + 2] * P.Rq[3 * j + 2];
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) gR[3 * i + k] = P.M[i] * gA[k] + P.M[3 + i] * gA[3 + k];
  // Rq(qn) -> qn -> q
  {
    d4 w = P.qn[0], x = P.qn[1], y = P.qn[2], z = P.qn[3];
    const d4* G = gR;
    d4 gw = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
    d4 gx = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8]);
    d4 gy = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8]);
    d4 gz = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7]);
    d4 dot = w * gw + x * gx + y * gy + z * gz;
    gq[0] = (gw - w * dot) / P.qnorm;
    gq[1] = (gx - x * dot) / P.qnorm;
    gq[2] = (gy - y * dot) / P.qnorm;
    gq[3] = (gz - z * dot) / P.qnorm;
  }
  // M = J R: dL/dJ = gM R^T (only J00, J02, J11, J12 are not constant)
  const double* R = cam.R;
  d4 gJ00 = gM[0] * R[0] + gM[1] * R[1] + gM[2] * R[2];
  d4 gJ02 = gM[0] * R[6] + gM[1] * R[7] + gM[2] * R[8];
  d4 gJ11 = gM[3] * R[3] + gM[4] * R[4] + gM[5] * R[5];
  d4 gJ12 = gM[3] * R[6] + gM[4] * R[7] + gM[5] * R[8];
  const d4 x = P.p[0], y = P.p[1], iz = P.iz;
  d4 g_iz = cam.fx * (gJ00 - gJ02 * P.tx) + cam.fy * (gJ11 - gJ12 * P.ty) + gu * cam.fx * x + gv * cam.fy * y;
  d4 gx = gu * cam.fx * iz, gy = gv * cam.fy * iz;
  // where tx, ty were clamped, J does not depend on them
  const m4 in_x = (P.txr >= -cam.lim_x0) & (P.txr <= cam.lim_x1);
  const d4 g_tx = -gJ02 * cam.fx * iz;
  gx = dselect(in_x, gx + g_tx * iz, gx);
  g_iz = dselect(in_x, g_iz + g_tx * x, g_iz);
  const m4 in_y = (P.tyr >= -cam.lim_y0) & (P.tyr <= cam.lim_y1);
  const d4 g_ty = -gJ12 * cam.fy * iz;
  gy = dselect(in_y, gy + g_ty * iz, gy);
  g_iz = dselect(in_y, g_iz + g_ty * y, g_iz);
  d4 gzp = gz_direct - g_iz * iz * iz;
  for (int j = 0; j < 3; ++j) gm[j] = R[j] * gx + R[3 + j] * gy + R[6 + j] * gzp;
}

// Projects the Gaussians idx[0..n) (n <= 4; lanes past n repeat the last one) from the float
// inputs.
inline void project(const Camera& cam, Projection& P, const int32_t* idx, int n, const float* means,
                    const float* quats, const float* scales, d4* s = nullptr) {
  int64_t lanes[PROJECT_LANES];
  for (int k = 0; k < PROJECT_LANES; ++k) lanes[k] = idx[std::min(k, n - 1)];
  d4 m[3], q[4], sc[3];
  gather(means, 3, lanes, m);
  gather(quats, 4, lanes, q);
  gather(scales, 3, lanes, sc);
  project(cam, m, q, sc, P);
  if (s)
    for (int j = 0; j < 3; ++j) s[j] = sc[j];
}

// ------------------------------------------------------------------------------------------
// Per-Gaussian data in depth order, one cache line each

struct alignas(64) Splat {
  float u, v, a, b, c, det, level, boa;  // boa = b / a
  float logo, z, col[3];
  int32_t y0, y1;
  int32_t index;  // input index
};
static_assert(sizeof(Splat) == 64, "Splat is one cache line");

// A projected Gaussian's splat (2D mean u, v and conic a, b, c in pixels, camera depth z in
// metres); false when it covers no pixel of the W x H image.
inline bool make_splat(double u, double v, double a, double b, double c, double z, float o, const float* col,
                       int32_t index, int W, int H, Splat& s) {
  s.u = (float)u;
  s.v = (float)v;
  s.a = (float)a;
  s.b = (float)b;
  s.c = (float)c;
  s.z = (float)z;
  s.level = 2.0f * std::log(255.0f * o);
  s.logo = std::log(o);
  s.det = s.a * s.c - s.b * s.b;
  s.boa = s.b / s.a;
  for (int k = 0; k < 3; ++k) s.col[k] = col[k];
  s.index = index;
  float lv = s.level > 0.0f ? s.level : 0.0f;
  float ry = std::sqrt(lv * s.a / s.det);
  float rx = std::sqrt(lv * s.c / s.det);
  float y0 = std::ceil(s.v - ry), y1 = std::floor(s.v + ry);
  y0 = y0 > 0.0f ? y0 : 0.0f;
  y1 = y1 < (float)(H - 1) ? y1 : (float)(H - 1);
  const bool finite = std::isfinite(s.u) && std::isfinite(s.v) && std::isfinite(s.a) && std::isfinite(s.b) &&
                      std::isfinite(s.c) && std::isfinite(s.det) && std::isfinite(s.boa) && std::isfinite(s.z);
  if (!(finite && s.level > 0.0f && y1 >= y0 && std::floor(s.u + rx) >= 0.0f && std::ceil(s.u - rx) <= (float)(W - 1)))
    return false;
  s.y0 = (int32_t)y0;
  s.y1 = (int32_t)y1;
  return true;
}

// For the 16 image rows y0 + i: the covered columns [xl[i], xr[i]] (empty where xr < xl) and
// the rows' constants of log alpha = row_k - dx (a dx + row_b) / 2 with dx = x - xl + row_dx.
// The float32 operations and their order are the torch backend's (so the covered pixels are
// exactly the same); the loop is vectorised across rows.
struct RowSpans {
  alignas(64) float dy[TILE];
  alignas(64) float row_dx[TILE];
  alignas(64) float row_k[TILE];
  alignas(64) float row_b[TILE];
  alignas(64) int32_t xl[TILE];
  alignas(64) int32_t xr[TILE];
};

// ------------------------------------------------------------------------------------------
// One tile row = 16 pixels = one vector (slk_vec16.h: vf, vi and their helpers)

static_assert(TILE * sizeof(float) == sizeof(vf), "a tile row is one vector");

// exp for G blocks of float lanes (Cephes' expf: range reduction by ln 2, degree-6 polynomial;
// within ~1 ulp of the correctly rounded value on [-87, 0], which is all that alpha needs). The G
// are computed stage by stage: their dependency chains (~60 cycles each) interleave, where one
// exp at a time leaves the compositing loop waiting on its chain.
template <int G>
inline void vexp(vblock* x) {
  vblock n[G], r[G], p[G];
  iblock e[G];
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) {
    x[k] = select(x[k] < -87.0f, block_of(-87.0f), x[k]);
    const vblock t = x[k] * 1.44269504088896341f + 12582912.0f;  // 1.5 * 2^23: rounds x log2(e) to an integer
    n[k] = t - 12582912.0f;
    e[k] = (as_vi(t) - 0x4B400000 + 127) << 23;  // the bits of 2^n
  }
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) r[k] = vfma(n[k], block_of(-0.693359375f), x[k]);
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) r[k] = vfma(n[k], block_of(2.12194440e-4f), r[k]);
  // the polynomial by Estrin's scheme (three levels deep, not Horner's six: this chain is what the
  // compositing loops wait for)
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) {
    const vblock r2 = r[k] * r[k];
    const vblock hi = vfma(block_of(1.9875691500E-4f), r[k], block_of(1.3981999507E-3f));
    const vblock mid = vfma(block_of(8.3334519073E-3f), r[k], block_of(4.1665795894E-2f));
    const vblock lo = vfma(block_of(1.6666665459E-1f), r[k], block_of(5.0000001201E-1f));
    p[k] = vfma(vfma(hi, r2, mid), r2, lo);
    x[k] = (vfma(p[k], r2, r[k]) + 1.0f) * as_vf(e[k]);
  }
}

inline vf vclamp(vf x, float lo, float hi) {
  x = select(x < lo, vf1(lo), x);
  return select(x > hi, vf1(hi), x);
}

// exact ceil / floor for |x| < 2^31 (truncation toward zero, then corrected)
inline vf vceil(vf x) {
  const vf t = to_vf(to_vi(x));
  return t + select(t < x, vf1(1.0f), vf{});
}
inline vf vfloor(vf x) {
  const vf t = to_vf(to_vi(x));
  return t - select(t > x, vf1(1.0f), vf{});
}

// the rows' spans (see RowSpans): the torch backend's float32 operations, 16 rows at once
inline void row_spans(const Splat& s, int y0, int W, RowSpans& o) {
  const float a_level = s.a * s.level, wmax = (float)(W - 1);
  const vf dy = to_vf(LANE + y0) - s.v;
  const vf disc = a_level - s.det * dy * dy;
  const vf half = vsqrt(select(disc > 0.0f, disc, vf{})) / s.a;
  const vf mid = s.u - s.boa * dy;
  // clamping the bounds to [-1, W] first changes no result below (they are clamped to
  // [0, W - 1] after rounding) and keeps the float -> int conversions in range
  vf xl = vceil(vclamp(mid - half, -1.0f, (float)W));
  vf xr = vfloor(vclamp(mid + half, -1.0f, (float)W));
  xl = select(xl > 0.0f, xl, vf{});
  xr = select(xr < wmax, xr, vf1(wmax));
  const vi ok = xr >= xl;
  *(vf*)o.dy = dy;
  *(vf*)o.row_dx = xl - s.u;
  *(vf*)o.row_k = s.logo - 0.5f * s.c * dy * dy;
  *(vf*)o.row_b = 2.0f * s.b * dy;
  *(vi*)o.xl = select(ok, to_vi(xl), vi1(1));
  *(vi*)o.xr = select(ok, to_vi(xr), vi{});
}

// Compositing a tile goes chunk by chunk (CHUNK entries): the entries' row spans are computed
// (16 rows at once) and, per tile row, the entries covering it are listed, so that each row is
// then composited with its state in registers.
constexpr int CHUNK = 32;
constexpr int PREFETCH = 8;  // entries ahead whose splat is prefetched (they are scattered in memory)
struct ChunkEntry {
  RowSpans sp;
  float a, col[3], z;
  int32_t pos;  // position in the tile list
};

// The lanes of a tile row are processed a block at a time (slk_vec16.h: the whole row with
// AVX-512, else each 8-lane half that the entry's span meets; a span covers ~5-7 of the 16
// pixels on average, so most need one half).
constexpr int BLOCK = TILE / HALVES;

// Whether a row span [a, z] in tile columns (empty where z < a) meets block h within the tile's
// tw columns (no short-circuit: the outcomes are too irregular to predict, and the caller appends
// without a branch).
inline bool span_meets(int a, int z, int tw, int h) {
  return (z >= a) & (a < std::min(tw, (h + 1) * BLOCK)) & (z >= h * BLOCK);
}

// dx of the block of row lr whose first lane is lane0: lane - span start a + row_dx (a = xl - x0)
inline vblock block_dx(const RowSpans& sp, int lr, int a, int lane0) {
  return to_vf(block_lanes() + (lane0 - a)) + sp.row_dx[lr];
}

// alpha and dx of the block of row lr of G entries (first lane lane0, span starts a); log alpha is
// the torch backend's expression (fused here: it does not decide which pixels are covered).
// Computed G at a time so that their exps interleave (vexp).
template <int G>
inline void entry_alphas(const ChunkEntry* const* E, int lr, const int* a, int lane0, vblock* dx, vblock* al) {
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) {
    dx[k] = block_dx(E[k]->sp, lr, a[k], lane0);
    al[k] = vfma(dx[k] * -0.5f, vfma(dx[k], block_of(E[k]->a), block_of(E[k]->sp.row_b[lr])),
                 block_of(E[k]->sp.row_k[lr]));
  }
  vexp<G>(al);
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) al[k] = select(al[k] < ALPHA_MAX, al[k], block_of(ALPHA_MAX));
}

// entries whose alphas a compositing block computes at once
constexpr int GROUP = 4;

// The forward's alphas, kept for the backward, which would otherwise recompute every pair's exp
// (the longest dependency chain of its loop; ~40 % of its time). Blocks are stored in the order
// the forward composites them (so it writes sequentially): per tile chunk by chunk, per chunk
// by (row, half), per (row, half) the chunk's entries listed for it in depth order; the backward
// finds an entry's block from the chunk's list lengths (entry_rows). Each compositing thread
// appends its tiles' blocks to its own store (grown by doubling up to its share of the budget,
// never initialised: only the blocks composited are written, and the backward reads no other);
// a chunk that would exceed it is not stored, and the backward recomputes its alphas.
struct AlphaStore {
  std::unique_ptr<vblock[]> data;
  size_t size = 0, cap = 0;  // in blocks
  void reserve(size_t n, size_t budget) {
    if (n <= cap) return;
    const size_t c = std::max(n, std::min(2 * cap, budget));
    std::unique_ptr<vblock[]> d(new vblock[c]);
    std::atomic_thread_fence(std::memory_order_seq_cst);  // (the streaming stores so far, before they are read)
    if (cap) std::memcpy((void*)d.get(), (const void*)data.get(), cap * sizeof(vblock));  // the tile being written too
    data.swap(d);
    cap = c;
  }
};

// Reads the blocks [from, to) once, in address order, so that the hardware prefetcher streams
// them in: the backward then reads them in an order no prefetcher guesses (at 320x240, 3.7 ms
// of a 12.6 ms backward waited for them; software prefetches of the same lines did not help).
inline void stream_in(const vblock* from, const vblock* to) {
  float sink = 0.0f;
  for (const char* p = (const char*)from; p < (const char*)to; p += 64) sink += *(const float*)p;
  __asm__ __volatile__("" : : "g"(sink));  // (keeps the loads)
}

// A block written past the caches (non-temporal: the line is not read first; the backward reads
// it back much later); visible to other threads after fence_streaming().
inline void store_streaming(vblock* p, vblock v) {
#if defined(__AVX512F__)
  _mm512_stream_ps((float*)p, (__m512)v);
#elif defined(__AVX__)
  _mm256_stream_ps((float*)p, (__m256)v);
#else
  *p = v;
#endif
}
inline void fence_streaming() {
#if defined(__AVX512F__) || defined(__AVX__)
  _mm_sfence();
#endif
}

// Stores outlive the render that filled them and are handed to the next: a fresh store a render
// (~15 MB at 320x240) would cost a page fault every 4 KB, most of what keeping the alphas saves.
// The pool keeps about one render's worth (the budget of the render giving its stores back).
class AlphaStorePool {
 public:
  static AlphaStorePool& instance() {  // (as Pool::instance: never destroyed, one per process)
    static std::mutex m;
    static AlphaStorePool* pool = nullptr;
    static int64_t pid = -1;
    std::lock_guard<std::mutex> lock(m);
    const int64_t now = (int64_t)::getpid();
    if (pool == nullptr || pid != now) {  // a forked child must not wait on the parent's lock
      pool = new AlphaStorePool();
      pid = now;
    }
    return *pool;
  }
  AlphaStore take() {
    std::lock_guard<std::mutex> lock(mu_);
    if (free_.empty()) return AlphaStore();
    AlphaStore st = std::move(free_.back());
    free_.pop_back();
    kept_ -= st.cap;
    st.size = 0;
    return st;
  }
  // keeps `stores` while the pool holds at most `max_blocks` in all (the rest are freed)
  void give(std::vector<AlphaStore>& stores, size_t max_blocks) {
    std::lock_guard<std::mutex> lock(mu_);
    for (AlphaStore& st : stores)
      if (st.cap > 0 && kept_ + st.cap <= max_blocks) {
        kept_ += st.cap;
        free_.push_back(std::move(st));
      }
    stores.clear();
  }

 private:
  std::mutex mu_;
  std::vector<AlphaStore> free_;
  size_t kept_ = 0;  // blocks held by free_
};

struct State {
  int N = 0, M = 0, W = 0, H = 0, tiles_x = 0, tiles_y = 0;
  Camera cam;
  std::vector<Splat> splats;            // M, depth order
  std::vector<int32_t> tile_start;      // tiles + 1
  std::vector<int32_t> tile_ids;        // entries: splat index, depth order within a tile
  std::vector<int32_t> tile_slot;       // entries: slot of the entry (Gaussian-major order)
  std::vector<int32_t> sorted_of;       // N: depth rank of input Gaussian i, -1 if culled
  std::vector<int32_t> slot_start;      // M + 1: slots of splat i are [slot_start[i], slot_start[i+1])
  std::vector<int32_t> tile_order;      // tiles by decreasing list length (load balance)
  std::vector<float> T_final;           // H*W
  std::vector<int32_t> last;            // H*W: last composited position in the tile list, -1 none
  size_t alpha_budget = 0;              // blocks each forward thread may store (AlphaStore)
  std::vector<AlphaStore> alpha_store;  // per forward thread
  std::vector<int32_t> tile_store;      // tiles: the thread whose store holds the tile's alphas
  std::vector<int64_t> tile_block;      // tiles: the tile's first block in that store
  std::vector<int32_t> chunk_block;     // entries: at a chunk's first entry, its first block (-1: not stored)
  std::vector<uint32_t> entry_rows;     // entries: bit lr * HALVES + h set where the entry was listed
  int64_t num_pairs = 0;
  int64_t num_rows = 0;  // vector steps of the forward pass, in 16-lane units (an 8-lane half counts 1/2)
  int64_t num_rows_stored = 0;  // of those, the ones whose alphas were kept for the backward
  int threads_used = 0;  // threads that composited at least one tile in the forward pass
  // per phase (forward: project, sort, bin, lists, composite; backward: tiles, reduce): wall, CPU
  int64_t wall_us[8] = {0}, cpu_us[8] = {0};

  ~State() { AlphaStorePool::instance().give(alpha_store, alpha_budget * alpha_store.size()); }
};

void radix_sort_by_key(std::vector<uint32_t>& key, std::vector<int32_t>& val) {
  size_t n = key.size();
  std::vector<uint32_t> k2(n);
  std::vector<int32_t> v2(n);
  for (int shift = 0; shift < 32; shift += 11) {
    size_t count[2049] = {0};
    for (size_t i = 0; i < n; ++i) ++count[((key[i] >> shift) & 2047) + 1];
    for (int d = 0; d < 2048; ++d) count[d + 1] += count[d];
    for (size_t i = 0; i < n; ++i) {
      size_t j = count[(key[i] >> shift) & 2047]++;
      k2[j] = key[i];
      v2[j] = val[i];
    }
    key.swap(k2);
    val.swap(v2);
  }
}

inline uint32_t float_bits(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  return u;
}

// ------------------------------------------------------------------------------------------
// Forward

void forward(State& S, const float* means, const float* quats, const float* scales, const float* opac,
             const float* colors, const float* bg, int nthreads, float* out_color, float* out_depth,
             float* out_alpha) {
  const Camera& cam = S.cam;
  const int N = S.N, W = S.W, H = S.H;
  const float alpha_min = (float)(1.0 / 255.0);

  Stamp t0 = now_us();
  // 1. project, cull, per-Gaussian rasterisation constants
  std::vector<Splat> tmp(N);
  std::vector<uint8_t> valid(N, 0);
  parallel_for(nthreads, N, 4096, [&](int64_t b, int64_t e, int) {
    // the cheap culls first, then the survivors projected four at a time
    std::vector<int32_t> kept;
    kept.reserve(e - b);
    for (int64_t i = b; i < e; i += PROJECT_LANES) {
      int64_t idx[PROJECT_LANES];
      for (int k = 0; k < PROJECT_LANES; ++k) idx[k] = std::min<int64_t>(i + k, e - 1);
      const int bits = maybe_visible(cam, idx, means, scales);
      for (int k = 0; k < PROJECT_LANES && i + k < e; ++k)
        if ((bits >> k & 1) && opac[i + k] > alpha_min) kept.push_back((int32_t)(i + k));
    }
    Projection P;
    for (size_t g = 0; g < kept.size(); g += PROJECT_LANES) {
      const int n = (int)std::min<size_t>(PROJECT_LANES, kept.size() - g);
      project(cam, P, kept.data() + g, n, means, quats, scales);
      for (int k = 0; k < n; ++k) {
        const int32_t i = kept[g + k];
        valid[i] = make_splat(P.u[k], P.v[k], P.a[k], P.b[k], P.c[k], P.p[2][k], opac[i], colors + 3 * i, i, W, H,
                              tmp[i]);
      }
    }
  });

  Stamp t1 = now_us();
  // 2. sort by depth (stable: ties keep the input order), z > 0 so its bits sort as integers
  std::vector<uint32_t> key;
  std::vector<int32_t> order;
  key.reserve(N);
  order.reserve(N);
  for (int i = 0; i < N; ++i)
    if (valid[i]) {
      key.push_back(float_bits(tmp[i].z));
      order.push_back(i);
    }
  radix_sort_by_key(key, order);
  const int M = (int)order.size();
  S.M = M;
  S.sorted_of.assign(N, -1);
  for (int i = 0; i < M; ++i) S.sorted_of[order[i]] = i;
  S.splats.resize(M);
  std::vector<int32_t> band_start(M + 1);
  band_start[0] = 0;
  for (int i = 0; i < M; ++i) {
    const Splat& s = tmp[order[i]];
    band_start[i + 1] = band_start[i] + (s.y1 / TILE - s.y0 / TILE + 1);
  }
  std::vector<int16_t> band_x0(band_start[M]), band_x1(band_start[M]);
  std::vector<int32_t> entries_of(M);

  Stamp t2 = now_us();
  // 3. tile columns touched in each band of 16 rows, from the exact row intervals
  parallel_for(nthreads, M, 1024, [&](int64_t b, int64_t e, int) {
    RowSpans sp;
    for (int64_t i = b; i < e; ++i) {
      if (i + PREFETCH < e) __builtin_prefetch(&tmp[order[i + PREFETCH]]);
      const Splat& s = S.splats[i] = tmp[order[i]];
      int n = 0, k = band_start[i];
      for (int ty = s.y0 / TILE; ty <= s.y1 / TILE; ++ty, ++k) {
        const int r0 = std::max(s.y0 - ty * TILE, 0), r1 = std::min(s.y1 - ty * TILE, TILE - 1);
        row_spans(s, ty * TILE, W, sp);
        int lo = W, hi = -1;
        for (int lr = r0; lr <= r1; ++lr) {
          if (sp.xr[lr] < sp.xl[lr]) continue;
          lo = std::min(lo, sp.xl[lr]);
          hi = std::max(hi, sp.xr[lr]);
        }
        if (hi < lo) {
          band_x0[k] = 1;
          band_x1[k] = 0;
          continue;
        }
        band_x0[k] = (int16_t)(lo / TILE);
        band_x1[k] = (int16_t)(hi / TILE);
        n += band_x1[k] - band_x0[k] + 1;
      }
      entries_of[i] = n;
    }
  });
  tmp.clear();
  tmp.shrink_to_fit();

  Stamp t3 = now_us();
  // 4. tile lists in depth order, and each entry's slot (Gaussian-major) for the backward pass
  const int tiles = S.tiles_x * S.tiles_y;
  S.slot_start.assign(M + 1, 0);
  for (int i = 0; i < M; ++i) S.slot_start[i + 1] = S.slot_start[i] + entries_of[i];
  const int64_t num_entries = S.slot_start[M];
  S.tile_start.assign(tiles + 1, 0);
  for (int i = 0; i < M; ++i) {
    const Splat& s = S.splats[i];
    int k = band_start[i];
    for (int ty = s.y0 / TILE; ty <= s.y1 / TILE; ++ty, ++k)
      for (int tx = band_x0[k]; tx <= band_x1[k]; ++tx) ++S.tile_start[ty * S.tiles_x + tx + 1];
  }
  for (int t = 0; t < tiles; ++t) S.tile_start[t + 1] += S.tile_start[t];
  S.tile_ids.resize(num_entries);
  S.tile_slot.resize(num_entries);
  {
    std::vector<int32_t> cursor(S.tile_start.begin(), S.tile_start.end() - 1);
    int32_t slot = 0;
    for (int i = 0; i < M; ++i) {
      const Splat& s = S.splats[i];
      int k = band_start[i];
      for (int ty = s.y0 / TILE; ty <= s.y1 / TILE; ++ty, ++k)
        for (int tx = band_x0[k]; tx <= band_x1[k]; ++tx) {
          int32_t pos = cursor[ty * S.tiles_x + tx]++;
          S.tile_ids[pos] = i;
          S.tile_slot[pos] = slot++;
        }
    }
  }
  S.tile_order.resize(tiles);
  for (int t = 0; t < tiles; ++t) S.tile_order[t] = t;
  std::stable_sort(S.tile_order.begin(), S.tile_order.end(), [&](int p, int q) {
    return S.tile_start[p + 1] - S.tile_start[p] > S.tile_start[q + 1] - S.tile_start[q];
  });

  Stamp t4 = now_us();
  // 5. composite each tile
  S.T_final.resize((size_t)W * H);
  AlphaStorePool::instance().give(S.alpha_store, 0);  // (a State renders once; this keeps it safe)
  for (int t = 0; t < std::max(nthreads, 1); ++t)
    S.alpha_store.push_back(S.alpha_budget ? AlphaStorePool::instance().take() : AlphaStore());
  S.tile_store.assign(tiles, 0);
  S.tile_block.assign(tiles, 0);
  S.chunk_block.resize(num_entries);
  S.entry_rows.resize(num_entries);
  S.last.resize((size_t)W * H);
  std::vector<int64_t> pairs_per_thread(std::max(nthreads, 1), 0), lanes_per_thread(std::max(nthreads, 1), 0),
      stored_per_thread(std::max(nthreads, 1), 0),
      tiles_per_thread(std::max(nthreads, 1), 0);
  parallel_for(nthreads, tiles, 1, [&](int64_t b, int64_t e, int tid) {
    std::unique_ptr<ChunkEntry[]> ents(new ChunkEntry[CHUNK]);
    for (int64_t ti = b; ti < e; ++ti) {
      const int tile = S.tile_order[ti];
      const int tx = tile % S.tiles_x, ty = tile / S.tiles_x;
      const int x0 = tx * TILE, y0 = ty * TILE;
      const int tw = std::min(TILE, W - x0), th = std::min(TILE, H - y0);
      // per tile row: transmittance, colour, depth and alpha sums, last position, done lanes
      vf T[TILE], c0[TILE], c1[TILE], c2[TILE], dep[TILE], acc[TILE];
      vi last[TILE], done[TILE];
      bool alive[TILE][HALVES];  // blocks with lanes not done
      int blocks_alive = 0;
      const vi outside = LANE >= tw;
      for (int r = 0; r < TILE; ++r) {
        T[r] = vf1(1.0f);
        c0[r] = c1[r] = c2[r] = dep[r] = acc[r] = vf{};
        last[r] = vi1(-1);
        done[r] = r < th ? outside : vi1(-1);
        for (int h = 0; h < HALVES; ++h) blocks_alive += alive[r][h] = !all(block(done[r], h));
      }
      int64_t lanes = 0, stored_lanes = 0;
      iblock count = iblock{};
      AlphaStore& store = S.alpha_store[tid];
      S.tile_store[tile] = tid;
      S.tile_block[tile] = (int64_t)store.size;
      int32_t tile_blocks = 0;
      const int end = S.tile_start[tile + 1];
      for (int cs = S.tile_start[tile]; cs < end && blocks_alive > 0; cs += CHUNK) {
        // the chunk's entries: their row spans, and per tile row and block the ones covering it
        // in depth order (blocks already done are skipped)
        const int ce = std::min(end, cs + CHUNK);
        int nrow[TILE][HALVES] = {};
        uint8_t list[TILE][HALVES][CHUNK];
        for (int pos = cs; pos < ce; ++pos) {
          if (pos + PREFETCH < end) __builtin_prefetch(&S.splats[S.tile_ids[pos + PREFETCH]]);
          const Splat& s = S.splats[S.tile_ids[pos]];
          const int k = pos - cs;
          ChunkEntry& E = ents[k];
          const int r0 = std::max(s.y0 - y0, 0), r1 = std::min(s.y1 - y0, th - 1);
          row_spans(s, y0, W, E.sp);
          E.a = s.a;
          E.col[0] = s.col[0];
          E.col[1] = s.col[1];
          E.col[2] = s.col[2];
          E.z = s.z;
          E.pos = pos;
          uint32_t rows = 0;
          for (int lr = r0; lr <= r1; ++lr)
            for (int h = 0; h < HALVES; ++h) {
              const bool listed = alive[lr][h] & span_meets(E.sp.xl[lr] - x0, E.sp.xr[lr] - x0, tw, h);
              list[lr][h][nrow[lr][h]] = (uint8_t)k;  // (kept only when listed: branch-free)
              nrow[lr][h] += listed;
              rows |= (uint32_t)listed << (lr * HALVES + h);
            }
          S.entry_rows[pos] = rows;
        }
        // where the chunk's alphas go (AlphaStore)
        int row_block[TILE][HALVES], chunk_blocks = 0;
        for (int lr = 0; lr < TILE; ++lr)
          for (int h = 0; h < HALVES; ++h) {
            row_block[lr][h] = chunk_blocks;
            chunk_blocks += nrow[lr][h];
          }
        vblock* alphas = nullptr;
        const size_t stored = S.tile_block[tile] + tile_blocks + chunk_blocks;
        S.chunk_block[cs] = -1;
        if (stored <= S.alpha_budget) {
          store.reserve(stored, S.alpha_budget);
          alphas = store.data.get() + S.tile_block[tile] + tile_blocks;
          S.chunk_block[cs] = tile_blocks;
          tile_blocks += chunk_blocks;
        }
        // composite block by block, the block's state in registers
        for (int lr = 0; lr < th; ++lr)
          for (int h = 0; h < HALVES; ++h) {
            const int n = nrow[lr][h];
            if (n == 0) continue;
            lanes += n * BLOCK;
            stored_lanes += alphas ? n * BLOCK : 0;
            const int lane0 = h * BLOCK;
            const iblock lane = block_lanes() + lane0;
            vblock rT = block(T[lr], h), r0c = block(c0[lr], h), r1c = block(c1[lr], h), r2c = block(c2[lr], h),
                   rdep = block(dep[lr], h), racc = block(acc[lr], h);
            iblock rlast = block(last[lr], h), rdone = block(done[lr], h);
            for (int j0 = 0; j0 < n; j0 += GROUP) {
              // a group's alphas first (the last group padded with its last entry, not composited)
              const ChunkEntry* G[GROUP];
              int a[GROUP];
              vblock dx[GROUP], al[GROUP];
              for (int k = 0; k < GROUP; ++k) {
                G[k] = &ents[list[lr][h][std::min(j0 + k, n - 1)]];
                a[k] = G[k]->sp.xl[lr] - x0;
              }
              entry_alphas<GROUP>(G, lr, a, lane0, dx, al);
              bool finished = false;
              for (int k = 0; k < std::min(GROUP, n - j0); ++k) {
                const ChunkEntry& E = *G[k];
                if (alphas) store_streaming(&alphas[row_block[lr][h] + j0 + k], al[k]);
                const iblock in = (lane >= a[k]) & (lane <= E.sp.xr[lr] - x0) & ~rdone;
                const vblock Tn = rT * (1.0f - al[k]);
                const iblock stop = in & (Tn < (float)T_MIN);
                const iblock m = in & ~stop;
                const vblock w = select(m, al[k] * rT, vblock{});
                r0c = vfma(w, block_of(E.col[0]), r0c);
                r1c = vfma(w, block_of(E.col[1]), r1c);
                r2c = vfma(w, block_of(E.col[2]), r2c);
                rdep = vfma(w, block_of(E.z), rdep);
                racc += w;
                rT = select(m, Tn, rT);
                rlast = select(m, iblock{} + E.pos, rlast);
                count -= m;
                rdone |= stop;  // (branch-free: stops are too frequent and irregular to predict)
                if (all(rdone)) {
                  finished = true;
                  break;
                }
              }
              if (finished) {
                alive[lr][h] = false;
                --blocks_alive;
                break;
              }
            }
            block(T[lr], h) = rT;
            block(c0[lr], h) = r0c;
            block(c1[lr], h) = r1c;
            block(c2[lr], h) = r2c;
            block(dep[lr], h) = rdep;
            block(acc[lr], h) = racc;
            block(last[lr], h) = rlast;
            block(done[lr], h) = rdone;
          }
      }
      store.size = S.tile_block[tile] + tile_blocks;
      for (int lr = 0; lr < th; ++lr)
        for (int lc = 0; lc < tw; ++lc) {
          const size_t q = (size_t)(y0 + lr) * W + (x0 + lc);
          // the background shows through T = 1 - sum w (T is the more accurate where alpha ~ 1)
          const float rest = T[lr][lc];
          out_color[3 * q] = c0[lr][lc] + rest * bg[0];
          out_color[3 * q + 1] = c1[lr][lc] + rest * bg[1];
          out_color[3 * q + 2] = c2[lr][lc] + rest * bg[2];
          out_depth[q] = dep[lr][lc];
          out_alpha[q] = acc[lr][lc];
          S.T_final[q] = T[lr][lc];
          S.last[q] = last[lr][lc];
        }
      int64_t pairs = 0;
      for (int i = 0; i < BLOCK; ++i) pairs += count[i];
      pairs_per_thread[tid] += pairs;
      lanes_per_thread[tid] += lanes;
      stored_per_thread[tid] += stored_lanes;
      tiles_per_thread[tid] += 1;
    }
    fence_streaming();  // the alphas, for the backward
  });
  S.num_pairs = 0;
  for (int64_t p : pairs_per_thread) S.num_pairs += p;
  S.num_rows = 0;
  for (int64_t r : lanes_per_thread) S.num_rows += r;
  S.num_rows /= TILE;  // in 16-lane steps
  S.num_rows_stored = 0;
  for (int64_t r : stored_per_thread) S.num_rows_stored += r;
  S.num_rows_stored /= TILE;
  S.threads_used = 0;
  for (int64_t t : tiles_per_thread) S.threads_used += t > 0;
  Stamp t5 = now_us();
  S.wall_us[0] = t1.wall - t0.wall;
  S.cpu_us[0] = t1.cpu - t0.cpu;
  S.wall_us[1] = t2.wall - t1.wall;
  S.cpu_us[1] = t2.cpu - t1.cpu;
  S.wall_us[2] = t3.wall - t2.wall;
  S.cpu_us[2] = t3.cpu - t2.cpu;
  S.wall_us[3] = t4.wall - t3.wall;
  S.cpu_us[3] = t4.cpu - t3.cpu;
  S.wall_us[4] = t5.wall - t4.wall;
  S.cpu_us[4] = t5.cpu - t4.cpu;
}

// ------------------------------------------------------------------------------------------
// Backward

// A tile's alphas as the forward pass stored them (AlphaStore), for a walk of its list back to
// front: visit(pos) for each position walked, then next(bit) for each bit of entry_rows[pos] in
// increasing order gives that block's alphas, where stored().
class StoredAlphas {
 public:
  StoredAlphas(const State& S, int tile)
      : S_(S), tile_(S.alpha_store[S.tile_store[tile]].data.get() + S.tile_block[tile]),
        start_(S.tile_start[tile]), end_(S.tile_start[tile + 1]) {}

  void visit(int pos) {
    const int cs = start_ + (pos - start_) / CHUNK * CHUNK;
    if (cs == chunk_start_) return;
    // the first position visited in this chunk: the chunk's blocks per (row, half) in all, and
    // up to this position (the forward numbered them row by row, each row in list order)
    chunk_start_ = cs;
    int listed[TILE * HALVES] = {};
    for (int q = cs; q < std::min(end_, cs + CHUNK); ++q) {
      for (uint32_t rows = S_.entry_rows[q]; rows; rows &= rows - 1) ++listed[__builtin_ctz(rows)];
      if (q == pos) std::memcpy(before_, listed, sizeof before_);
    }
    int n = 0;
    for (int b = 0; b < TILE * HALVES; ++b) {
      row_block_[b] = n;
      n += listed[b];
    }
    chunk_ = S_.chunk_block[cs] < 0 ? nullptr : tile_ + S_.chunk_block[cs];
    if (chunk_) stream_in(chunk_, chunk_ + n);
  }
  bool stored() const { return chunk_ != nullptr; }  // false: over the budget, to be recomputed
  const vblock* next(int bit) { return chunk_ + row_block_[bit] + --before_[bit]; }  // where stored()

 private:
  const State& S_;
  const vblock* tile_;               // the tile's first block
  const vblock* chunk_ = nullptr;    // the current chunk's first block
  int start_, end_, chunk_start_ = -1;
  int row_block_[TILE * HALVES];     // per (row, half): its first block in the chunk
  int before_[TILE * HALVES];        // per (row, half): the chunk's entries listed for it before the current
};

void backward(State& S, const float* means, const float* quats, const float* scales, const float* opac,
              const float* g_color, const float* g_depth, const float* g_alpha, const float* bg, int nthreads,
              float* g_means, float* g_quats, float* g_scales, float* g_opac, float* g_colors, float* g_bg) {
  const int W = S.W, H = S.H;
  const int tiles = S.tiles_x * S.tiles_y;
  const int64_t num_entries = S.tile_ids.size();
  Stamp t0 = now_us();
  std::unique_ptr<float[]> moments(new float[(size_t)num_entries * NUM_MOMENTS]);  // every slot is written
  std::vector<double> bg_tile(3 * (size_t)tiles);

  // 1. per tile, back to front: per-entry moments
  parallel_for(nthreads, tiles, 1, [&](int64_t b, int64_t e, int) {
    for (int64_t ti = b; ti < e; ++ti) {
      const int tile = S.tile_order[ti];
      const int tx = tile % S.tiles_x, ty = tile / S.tiles_x;
      const int x0 = tx * TILE, y0 = ty * TILE;
      const int tw = std::min(TILE, W - x0), th = std::min(TILE, H - y0);
      const int start = S.tile_start[tile], end = S.tile_start[tile + 1];
      // per tile row: transmittance (after the current entry), suffix sum of w v, output grads
      vf T[TILE], Ssum[TILE], g0[TILE], g1[TILE], g2[TILE], gd[TILE], ga[TILE];
      vi last[TILE];
      int maxlast = -1;
      for (int lr = 0; lr < TILE; ++lr) {
        T[lr] = Ssum[lr] = g0[lr] = g1[lr] = g2[lr] = gd[lr] = ga[lr] = vf{};
        last[lr] = vi1(-1);
      }
      for (int lr = 0; lr < th; ++lr)
        for (int lc = 0; lc < tw; ++lc) {
          const size_t q = (size_t)(y0 + lr) * W + (x0 + lc);
          T[lr][lc] = S.T_final[q];
          g0[lr][lc] = g_color[3 * q];
          g1[lr][lc] = g_color[3 * q + 1];
          g2[lr][lc] = g_color[3 * q + 2];
          gd[lr][lc] = g_depth[q];
          // d colour / d (sum w) = -bg, folded into the alpha gradient
          ga[lr][lc] = g_alpha[q] - (g_color[3 * q] * bg[0] + g_color[3 * q + 1] * bg[1] + g_color[3 * q + 2] * bg[2]);
          last[lr][lc] = S.last[q];
          maxlast = std::max(maxlast, S.last[q]);
        }
      {
        double b0 = 0, b1 = 0, b2 = 0;  // d colour / d bg = T
        for (int lr = 0; lr < th; ++lr)
          for (int lc = 0; lc < tw; ++lc) {
            b0 += (double)T[lr][lc] * g0[lr][lc];
            b1 += (double)T[lr][lc] * g1[lr][lc];
            b2 += (double)T[lr][lc] * g2[lr][lc];
          }
        bg_tile[3 * tile] = b0;
        bg_tile[3 * tile + 1] = b1;
        bg_tile[3 * tile + 2] = b2;
      }
      ChunkEntry E;
      const RowSpans& sp = E.sp;
      StoredAlphas alphas(S, tile);
      for (int pos = end - 1; pos >= start; --pos) {
        float* mom = &moments[(size_t)S.tile_slot[pos] * NUM_MOMENTS];
        if (pos > maxlast) {
          for (int k = 0; k < NUM_MOMENTS; ++k) mom[k] = 0.0f;
          continue;
        }
        if (pos - PREFETCH >= start) __builtin_prefetch(&S.splats[S.tile_ids[pos - PREFETCH]]);
        const Splat& s = S.splats[S.tile_ids[pos]];
        // the entry's moments, summed over its rows and blocks (lane by lane, then across)
        vblock m0{}, mx{}, my{}, mxx{}, mxy{}, myy{}, w0{}, w1{}, w2{}, wd{};
        const iblock posv = iblock{} + pos;
        row_spans(s, y0, W, E.sp);
        E.a = s.a;
        alphas.visit(pos);
        // the blocks the forward pass listed the entry in (it composited those this walk needs),
        // with the alphas it stored or recomputed (a loop for each: no test per block)
        auto entry_blocks = [&](auto stored_alphas) {
          for (uint32_t rows = S.entry_rows[pos]; rows; rows &= rows - 1) {
            const int bit = __builtin_ctz(rows), lr = bit / HALVES, h = bit % HALVES;
            const vblock* stored = nullptr;
            if constexpr (decltype(stored_alphas)::value) stored = alphas.next(bit);
            const int a = sp.xl[lr] - x0, z = sp.xr[lr] - x0;  // the span in tile columns
            const int lane0 = h * BLOCK;
            const iblock lane = block_lanes() + lane0;
            const iblock m = (lane >= a) & (lane <= z) & (posv <= block(last[lr], h));
            if (!any(m)) continue;
            vblock dx, al;
            if constexpr (decltype(stored_alphas)::value) {
              al = *stored;
              dx = block_dx(sp, lr, a, lane0);
            } else {
              const ChunkEntry* e = &E;
              entry_alphas<1>(&e, lr, &a, lane0, &dx, &al);
            }
            const vblock dy = block_of(sp.dy[lr]);
            const vblock inv = 1.0f / (1.0f - al);
            vblock& Tr = block(T[lr], h);
            vblock& Sr = block(Ssum[lr], h);
            const vblock G0 = block(g0[lr], h), G1 = block(g1[lr], h), G2 = block(g2[lr], h);
            const vblock Tb = Tr * inv;  // transmittance before this Gaussian
            const vblock w = select(m, al * Tb, vblock{});
            const vblock GD = block(gd[lr], h), GA = block(ga[lr], h);
            const vblock val_c2 = vfma(block_of(s.col[2]), G2, vfma(block_of(s.z), GD, GA));
            const vblock val = vfma(block_of(s.col[0]), G0, vfma(block_of(s.col[1]), G1, val_c2));
            // dL/dlog(alpha) = alpha dL/dalpha = alpha (T v - sum_{j>i} w_j v_j / (1 - alpha)), zero
            // where alpha is clamped
            const vblock sg = select(m & (al < ALPHA_MAX), al * vfma(Tb, val, -(Sr * inv)), vblock{});
            const vblock dxm = select(m, dx, vblock{});
            const vblock sdx = sg * dxm;
            const vblock sdy = sg * dy;
            m0 += sg;
            mx += sdx;
            my += sdy;
            mxx = vfma(sdx, dxm, mxx);
            mxy = vfma(sdx, dy, mxy);
            myy = vfma(sdy, dy, myy);
            w0 = vfma(w, G0, w0);
            w1 = vfma(w, G1, w1);
            w2 = vfma(w, G2, w2);
            wd = vfma(w, GD, wd);
            Sr = vfma(w, val, Sr);  // w = 0 outside m
            Tr = select(m, Tb, Tr);
          }
        };
        if (alphas.stored())
          entry_blocks(std::true_type{});
        else
          entry_blocks(std::false_type{});
        mom[0] = hsum(m0);
        mom[1] = hsum(mx);
        mom[2] = hsum(my);
        mom[3] = hsum(mxx);
        mom[4] = hsum(mxy);
        mom[5] = hsum(myy);
        mom[6] = hsum(w0);
        mom[7] = hsum(w1);
        mom[8] = hsum(w2);
        mom[9] = hsum(wd);
      }
    }
  });

  for (int k = 0; k < 3; ++k) {
    double sum = 0;
    for (int t = 0; t < tiles; ++t) sum += bg_tile[3 * t + k];
    g_bg[k] = (float)sum;
  }
  Stamp t1 = now_us();
  // 2. per Gaussian, in input order (the inputs and outputs stream; the sorted-side data is
  // prefetched): reduce its slots (fixed order), then the projection's backward
  const Camera& cam = S.cam;
  const int N = S.N;
  parallel_for(nthreads, N, 2048, [&](int64_t b, int64_t e, int) {
    // the slots reduced Gaussian by Gaussian, then the projection's backward four at a time
    std::vector<int32_t> kept;
    std::vector<double> g2d;  // per kept Gaussian: dL/d(u, v, a, b, c, z)
    kept.reserve(e - b);
    g2d.reserve(6 * (e - b));
    for (int64_t i = b; i < e; ++i) {
      if (i + 2 * PREFETCH < e) {
        const int32_t j2 = S.sorted_of[i + 2 * PREFETCH];
        if (j2 >= 0) {
          __builtin_prefetch(&S.splats[j2]);
          __builtin_prefetch(&S.slot_start[j2]);
        }
      }
      if (i + PREFETCH < e) {
        const int32_t j1 = S.sorted_of[i + PREFETCH];
        if (j1 >= 0) __builtin_prefetch(&moments[(size_t)S.slot_start[j1] * NUM_MOMENTS]);
      }
      for (int k = 0; k < 3; ++k) g_means[3 * i + k] = g_scales[3 * i + k] = g_colors[3 * i + k] = 0.0f;
      for (int k = 0; k < 4; ++k) g_quats[4 * i + k] = 0.0f;
      g_opac[i] = 0.0f;
      const int32_t j = S.sorted_of[i];
      if (j < 0) continue;  // culled: no gradient
      double m[NUM_MOMENTS] = {0};
      for (int32_t k = S.slot_start[j]; k < S.slot_start[j + 1]; ++k)
        for (int q = 0; q < NUM_MOMENTS; ++q) m[q] += moments[(size_t)k * NUM_MOMENTS + q];
      const Splat& s = S.splats[j];
      const double a = s.a, bb = s.b, c = s.c;
      kept.push_back((int32_t)i);
      g2d.insert(g2d.end(), {a * m[1] + bb * m[2], bb * m[1] + c * m[2], -0.5 * m[3], -m[4], -0.5 * m[5], m[9]});
      g_opac[i] = (float)(m[0] / (double)opac[i]);
      g_colors[3 * i] = (float)m[6];
      g_colors[3 * i + 1] = (float)m[7];
      g_colors[3 * i + 2] = (float)m[8];
    }
    Projection P;
    for (size_t g = 0; g < kept.size(); g += PROJECT_LANES) {
      const int n = (int)std::min<size_t>(PROJECT_LANES, kept.size() - g);
      d4 s[3], grad[6], gm[3], gq[4], gs[3];
      project(cam, P, kept.data() + g, n, means, quats, scales, s);
      for (int k = 0; k < PROJECT_LANES; ++k)
        for (int q = 0; q < 6; ++q) grad[q][k] = g2d[6 * (g + std::min(k, n - 1)) + q];
      project_backward(cam, P, s, grad[0], grad[1], grad[2], grad[3], grad[4], grad[5], gm, gq, gs);
      for (int k = 0; k < n; ++k) {
        const int64_t i = kept[g + k];
        for (int j = 0; j < 3; ++j) g_means[3 * i + j] += (float)gm[j][k];
        for (int j = 0; j < 4; ++j) g_quats[4 * i + j] += (float)gq[j][k];
        for (int j = 0; j < 3; ++j) g_scales[3 * i + j] += (float)gs[j][k];
      }
    }
  });
  Stamp t2 = now_us();
  S.wall_us[5] = t1.wall - t0.wall;
  S.cpu_us[5] = t1.cpu - t0.cpu;
  S.wall_us[6] = t2.wall - t1.wall;
  S.cpu_us[6] = t2.cpu - t1.cpu;
}

void write_error(char* err, int errlen, const char* msg) {
  if (err && errlen > 0) std::snprintf(err, (size_t)errlen, "%s", msg);
}

}  // namespace

// ------------------------------------------------------------------------------------------
// C ABI. All arrays are contiguous float32 (viewmat, intrinsics float64); every output array
// is written in full. Functions return 0 / a handle, or -1 / NULL with a message in err.

extern "C" {

int slk_abi_version() { return ABI_VERSION; }

// alpha_bytes: how much of its alphas the forward pass may keep for a backward pass (AlphaStore;
// all threads together; 0 where no backward follows, or to have the backward recompute them)
void* slk_forward(int N, const float* means, const float* quats, const float* scales, const float* opac,
                  const float* colors, const double* viewmat, const double* intr, int W, int H, const float* bg,
                  int nthreads, int64_t alpha_bytes, float* out_color, float* out_depth, float* out_alpha,
                  int64_t* stats, char* err, int errlen) {
  State* S = nullptr;
  try {
    S = new State();
    S->N = N;
    S->W = W;
    S->H = H;
    S->tiles_x = (W + TILE - 1) / TILE;
    S->tiles_y = (H + TILE - 1) / TILE;
    S->cam = make_camera(viewmat, intr, W, H);
    S->alpha_budget = (size_t)std::max<int64_t>(alpha_bytes, 0) / sizeof(vblock) / std::max(1, nthreads);
    forward(*S, means, quats, scales, opac, colors, bg, std::max(1, nthreads), out_color, out_depth, out_alpha);
    stats[0] = S->num_pairs;
    stats[1] = S->M;
    stats[2] = (int64_t)S->tile_ids.size();
    stats[3] = S->num_rows;
    stats[4] = S->threads_used;
    stats[5] = S->num_rows_stored;
    return S;
  } catch (const std::exception& e) {
    write_error(err, errlen, e.what());
  } catch (...) {
    write_error(err, errlen, "unknown error");
  }
  delete S;
  return nullptr;
}

int slk_backward(void* state, const float* means, const float* quats, const float* scales, const float* opac,
                 const float* g_color, const float* g_depth, const float* g_alpha, const float* bg, int nthreads,
                 float* g_means, float* g_quats, float* g_scales, float* g_opac, float* g_colors, float* g_bg,
                 char* err, int errlen) {
  try {
    State& S = *static_cast<State*>(state);
    backward(S, means, quats, scales, opac, g_color, g_depth, g_alpha, bg, std::max(1, nthreads), g_means, g_quats,
             g_scales, g_opac, g_colors, g_bg);
    return 0;
  } catch (const std::exception& e) {
    write_error(err, errlen, e.what());
  } catch (...) {
    write_error(err, errlen, "unknown error");
  }
  return -1;
}

// per-phase wall (out[0:8]) and process CPU (out[8:16]) microseconds of the last passes
void slk_times(void* state, int64_t* out) {
  const State& S = *static_cast<const State*>(state);
  for (int i = 0; i < 8; ++i) {
    out[i] = S.wall_us[i];
    out[8 + i] = S.cpu_us[i];
  }
}

void slk_free(void* state) { delete static_cast<State*>(state); }

}  // extern "C"
