// Camera and projection of the CPU rasteriser (cpu_rasterizer.cpp): the EWA projection of 3D
// Gaussians to 2D conics and its analytic backward, in double precision, four Gaussians at a time.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "conventions.h"

namespace {

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

}  // namespace
