// slamkit fused RGB-D mapping loss: value and gradients in one pass, no autograd graph.
//
// Plain C++17 with a C ABI (loaded with ctypes by slamkit_plugins/mappers/gaussian_splatting/loss/fused_rgbd_loss.py,
// which holds the torch reference `torch_rgbd_loss`). The loss, for rendered colour c (H,W,3),
// rendered depth d (H,W), keyframe image I (H,W,3) and observed depth D (H,W) in metres:
//
//   m = D > 0 (all ones, and no depth term, when no pixel has depth), n = sum m
//   L1   = sum |c - I| m / (3 n)
//   SSIM = pytorch_msssim.ssim(c m, I m): 11-tap separable Gaussian window (taps passed in),
//          "valid" filtering ((H-10) x (W-10) map), C1 = 0.01^2, C2 = 0.03^2, mean over the map
//          and the 3 channels
//   Ld   = sum |d - D| m / n / depth_unit
//   loss = w_l1 L1 + w_ssim (1 - SSIM) + w_depth Ld
//
// SSIM, per channel with x = c m, y = I m and F the valid separable filter, from the means and
// variances of s = x + y and t = x - y (Var = F(.^2) - (F .)^2):
//   mu1, mu2 = (F s +- F t) / 2,  B1 = mu1^2 + mu2^2 + C1 = ((F s)^2 + (F t)^2) / 2 + C1,
//   A1 = 2 mu1 mu2 + C1 = ((F s)^2 - (F t)^2) / 2 + C1,  B2 = s11 + s22 + C2 = (Var s + Var t) / 2 + C2,
//   A2 = 2 s12 + C2 = B2 - Var t,  S = l cs,  l = A1 / B1,  cs = A2 / B2.
// Backward: with the per-pixel adjoints (times -w_ssim / map size) of S w.r.t. mu1, e = F(x x + y y)
// and d = F(t t) (each with the other two and mu2 fixed),
//   a_mu = 2 (cs (mu2 - mu1 l) / B1 - l (mu2 - mu1 cs) / B2),  a_e = l Var t / B2^2,  a_d = -l / B2,
//   mu2 - mu1 l = -F t (mu2 F s + C1) / B1,  mu2 - mu1 cs = -F t + mu1 Var t / B2,
//   dloss/dx = F^T a_mu + 2 x F^T a_e + 2 t F^T a_d,
// where F^T, the adjoint of a valid correlation, is the full correlation with the same taps
// (zero outside the map; the window is symmetric, so F^T filters with the same taps).
//
// Precision: Var s cancels (on a flat image region it is ~1e-4 of (F s)^2), so F s and F(s s)
// are filtered in double (s and s^2 are exact there) and Var s formed in double: computed in
// float32, as torch does, the gradients on real keyframes are only ~3e-5 from the exact ones.
// Nothing else cancels in these variables: t, F t and Var t are small where x ~ y; a_mu and a_e
// are small on flat regions and a_d ~ -1/C2 multiplies t there (with torch's F x, F(x x),
// F(x y) the three gradient terms are each ~1/C2 and cancel to ~1e-3 of that). So the rest (the
// t maps, S, the seeds, the adjoint correlations, the L1 and depth terms) is float32; sums over
// pixels are double. Gradients on real keyframes: 1-2e-6 from torch's float64 result.
//
// Layout: row bands, one per thread, handed out dynamically by a persistent pool (a worker
// that is not scheduled in time is not waited for). Each band streams its rows, four at a time
// (they share their vertical filters' loads: 14 rows read for 4 instead of 44): deinterleave
// input rows into planar, masked channel rows (a ring of 14), filter vertically then
// horizontally, compute S and its three adjoints, correlate those horizontally (a ring of 14
// rows), and once an input row has all 11 contributions, correlate vertically and write its
// gradient. A band recomputes the 10 map rows above it (the halo its first rows' gradients
// need). Every output and every sum has a fixed order of operations, so results do not depend
// on the number of threads.
//
// Vectors: 64 bytes (16 floats, 8 doubles; slamkit/csrc/slk_vec16.h): AVX-512 with
// -march=native, two AVX2 registers where AVX-512 is missing. Fused multiply-adds where the CPU
// has them, so the native and the portable build differ in the last bits.

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <new>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <thread>
#include <vector>

#include <unistd.h>

#include "slk_thread_pool.h"  // (slamkit/csrc) Pool
#include "slk_vec16.h"        // (slamkit/csrc) vf, vd, vi and their helpers

namespace {

constexpr int ABI_VERSION = 1;
constexpr int K = 11;      // SSIM window taps
constexpr int R = K - 1;   // rows / columns the valid filter loses
constexpr int VL = 16;     // floats per vector
constexpr int VD = 8;      // doubles per vector
// Map rows (and input rows) computed together, sharing their loads. Measured here: 2 rows at a
// time 13-20 % slower, 6 the same, 8 5-7 % slower (registers run out).
constexpr int ROWS = 4;
constexpr int RING = K + ROWS - 1;  // input rows and correlated seed rows kept

// f.template operator()<N>() for the runtime n in 1..ROWS (the row count is a template
// parameter of the hot loops)
template <int N = ROWS, class F>
inline void with_rows(int n, F&& f) {
  if constexpr (N > 1) {
    if (n < N) return with_rows<N - 1>(n, f);
  }
  f(std::integral_constant<int, N>{});
}
constexpr double C1 = 0.01 * 0.01;  // (K1 data_range)^2, (K2 data_range)^2 as pytorch_msssim
constexpr double C2 = 0.03 * 0.03;

// sign(v) as torch's abs backward: 0 at 0, NaN for NaN
inline vf sign(vf v) { return select(v > 0, vf1(1.f), select(v < 0, vf1(-1.f), v)); }
inline vf vabs(vf v) { return as_vf(as_vi(v) & vi1(0x7fffffff)); }
// a += v, the 16 floats widened to double (low and high halves added first: a fixed order)
inline void add_wide(vd& a, vf v) {
  vd lo, hi;
  widen(v, lo, hi);
  a += lo + hi;
}
inline int round_up(int x, int m) { return (x + m - 1) / m * m; }

// The symmetric window (g[t] = g[10 - t]) applied to the 11 values at(0..10):
// g5 p5 + sum_{t<5} g_t (p_t + p_{10-t}), the centre first.
template <class V, class At>
inline V sym_filter(const V* g, At at) {
  V acc = g[5] * at(5);
  for (int t = 4; t >= 0; --t) acc = vfma(g[t], at(t) + at(K - 1 - t), acc);
  return acc;
}

// The same for the squares p_t^2: sum_t g_t p_t^2.
template <class V>
inline V sym_filter_squares(const V* g, const V* p) {
  V acc = g[5] * (p[5] * p[5]);
  for (int t = 4; t >= 0; --t) acc = vfma(g[t], vfma(p[t], p[t], p[K - 1 - t] * p[K - 1 - t]), acc);
  return acc;
}

// Filtering along a row: out[j] = sum_t g[t] p[j + t], the 11 shifted windows of one output
// vector taken from aligned vectors by lane shifts (AVX-512 valign) rather than by 10 unaligned
// loads, each of which would straddle two cache lines.
#if defined(__AVX512F__)
template <int S>
inline vd shift(vd a, vd b) {  // lanes S..S+7 of (a, b)
  return (vd)_mm512_castsi512_pd(_mm512_alignr_epi64(_mm512_castpd_si512((__m512d)b), _mm512_castpd_si512((__m512d)a), S));
}
template <int S>
inline vf shift(vf a, vf b) {  // lanes S..S+15 of (a, b)
  return (vf)_mm512_castsi512_ps(_mm512_alignr_epi32(_mm512_castps_si512((__m512)b), _mm512_castps_si512((__m512)a), S));
}
inline vd row_filter(const vd* g, const double* p) {  // p: 64-byte aligned
  const vd a = loadu(p), b = loadu(p + VD), c = loadu(p + 2 * VD);
  const vd w[K] = {a, shift<1>(a, b), shift<2>(a, b), shift<3>(a, b), shift<4>(a, b), shift<5>(a, b),
                   shift<6>(a, b), shift<7>(a, b), b, shift<1>(b, c), shift<2>(b, c)};
  return sym_filter(g, [&](int t) { return w[t]; });
}
inline vf row_filter(const vf* g, const float* p) {  // p: 64-byte aligned
  const vf a = loadu(p), b = loadu(p + VL);
  const vf w[K] = {a, shift<1>(a, b), shift<2>(a, b), shift<3>(a, b), shift<4>(a, b), shift<5>(a, b),
                   shift<6>(a, b), shift<7>(a, b), shift<8>(a, b), shift<9>(a, b), shift<10>(a, b)};
  return sym_filter(g, [&](int t) { return w[t]; });
}
inline vf row_filter6(const vf* g, const float* p) {  // sum_t g[t] p[j + 6 + t]; p: 64-byte aligned
  const vf a = loadu(p), b = loadu(p + VL);
  const vf w[K] = {shift<6>(a, b), shift<7>(a, b), shift<8>(a, b), shift<9>(a, b), shift<10>(a, b), shift<11>(a, b),
                   shift<12>(a, b), shift<13>(a, b), shift<14>(a, b), shift<15>(a, b), b};
  return sym_filter(g, [&](int t) { return w[t]; });
}
#else
inline vd row_filter(const vd* g, const double* p) {
  return sym_filter(g, [&](int t) { return loadu(p + t); });
}
inline vf row_filter(const vf* g, const float* p) {
  return sym_filter(g, [&](int t) { return loadu(p + t); });
}
inline vf row_filter6(const vf* g, const float* p) {
  return sym_filter(g, [&](int t) { return loadu(p + 6 + t); });
}
#endif

// (H,W,3) rows <-> planar channels, 16 pixels at a time: de/interleave3(p, ...) reads/writes
// p[0..47] as the channels' 16-lane vectors (two two-source permutes per vector).
#if defined(__AVX512F__)
inline vi lanes(int (*f)(int)) {
  alignas(64) int32_t v[VL];
  for (int k = 0; k < VL; ++k) v[k] = f(k);
  vi r;
  std::memcpy(&r, v, sizeof r);
  return r;
}
inline vf permute2(vf a, vi idx, vf b) {
  return (vf)_mm512_permutex2var_ps((__m512)a, (__m512i)idx, (__m512)b);
}
inline void deinterleave3(const float* p, vf out[3]) {
  // channel ch, lane k: element 3k + ch of (v0, v1, v2); those past 31 come in the second step
  static const vi first[3] = {lanes([](int k) { return 3 * k < 32 ? 3 * k : 0; }),
                              lanes([](int k) { return 3 * k + 1 < 32 ? 3 * k + 1 : 0; }),
                              lanes([](int k) { return 3 * k + 2 < 32 ? 3 * k + 2 : 0; })};
  static const vi second[3] = {lanes([](int k) { return 3 * k < 32 ? k : 3 * k - 16; }),
                               lanes([](int k) { return 3 * k + 1 < 32 ? k : 3 * k + 1 - 16; }),
                               lanes([](int k) { return 3 * k + 2 < 32 ? k : 3 * k + 2 - 16; })};
  const vf v0 = loadu(p), v1 = loadu(p + VL), v2 = loadu(p + 2 * VL);
  for (int ch = 0; ch < 3; ++ch) out[ch] = permute2(permute2(v0, first[ch], v1), second[ch], v2);
}
inline void interleave3(const vf in[3], float* p) {
  // output vector o, lane e: pixel (16 o + e) / 3, channel (16 o + e) % 3; channels 0 and 1
  // first (lanes of in[0], in[1]), then channel 2
  static const vi first[3] = {lanes([](int e) { return (e % 3 == 1 ? 16 : 0) + e / 3; }),
                              lanes([](int e) { return ((16 + e) % 3 == 1 ? 16 : 0) + (16 + e) / 3; }),
                              lanes([](int e) { return ((32 + e) % 3 == 1 ? 16 : 0) + (32 + e) / 3; })};
  static const vi second[3] = {lanes([](int e) { return e % 3 == 2 ? 16 + e / 3 : e; }),
                               lanes([](int e) { return (16 + e) % 3 == 2 ? 16 + (16 + e) / 3 : e; }),
                               lanes([](int e) { return (32 + e) % 3 == 2 ? 16 + (32 + e) / 3 : e; })};
  for (int o = 0; o < 3; ++o) storeu(p + o * VL, permute2(permute2(in[0], first[o], in[1]), second[o], in[2]));
}
#else
inline void deinterleave3(const float* p, vf out[3]) {
  float h[3][VL];
  for (int k = 0; k < VL; ++k)
    for (int ch = 0; ch < 3; ++ch) h[ch][k] = p[3 * k + ch];
  for (int ch = 0; ch < 3; ++ch) out[ch] = loadu(h[ch]);
}
inline void interleave3(const vf in[3], float* p) {
  float h[3][VL];
  for (int ch = 0; ch < 3; ++ch) storeu(h[ch], in[ch]);
  for (int k = 0; k < VL; ++k)
    for (int ch = 0; ch < 3; ++ch) p[3 * k + ch] = h[ch][k];
}
#endif

// 64-byte aligned, zero-initialised floats (rows start on a cache line: aligned vector loads).
struct Buffer {
  float* p = nullptr;
  explicit Buffer(size_t n) : p(static_cast<float*>(::operator new(n * sizeof(float), std::align_val_t(64)))) {
    std::fill_n(p, n, 0.f);
  }
  ~Buffer() { ::operator delete(p, std::align_val_t(64)); }
  Buffer(const Buffer&) = delete;
  Buffer& operator=(const Buffer&) = delete;
};

// The whole problem, shared by the bands (read-only but for each band's own output rows).
struct Problem {
  int H, W, Hv, Wv;
  int Wp;  // padded row length (elements, a multiple of 16): covers the filters' reads past the last vector
  const float *color, *depth, *image, *obs;
  vf gf[6];  // window taps 0..5 (symmetric), float and double
  vd gd[6];
  bool has_depth, do_ssim, grads;
  float k_l1, k_d, k_s;  // gradient scales: w_l1 / 3n, w_depth / (n unit), -w_ssim / (3 Hv Wv)
  float* grad_color;     // (H,W,3) or null
  float* grad_depth;     // (H,W) or null
  double *row_l1, *row_depth, *row_ssim;  // per-row sums (H, H, Hv)
};

// One band's rings and row buffers.
struct Band {
  const Problem& P;
  const int Wp, SL;  // SL: seed row length (map row at offset VL, zeros around)
  Buffer xy;    // [channel][x or y][ring slot][Wp]: x = c m, y = I m, planar
  Buffer mask;  // [ring slot][Wp]
  Buffer v;     // [ROWS][6 Wp]: a map row's vertical pass: F s, F s^2 (double), F t, F t^2 (float)
  Buffer seed;  // [3][SL]: a_mu, a_e, a_d of one map row
  Buffer u;     // [channel][ring slot][3][Wp]: the seeds correlated horizontally
  Buffer grad;  // [ROWS][3][Wp]: the rows' colour gradients, planar
  Buffer tail;  // [4 VL]: the last partial vector of an unpadded row

  explicit Band(const Problem& p)
      : P(p), Wp(p.Wp), SL(p.Wp + 2 * VL), xy((size_t)3 * 2 * RING * Wp), mask((size_t)RING * Wp),
        v((size_t)ROWS * 6 * Wp), seed((size_t)3 * SL), u((size_t)3 * RING * 3 * Wp), grad((size_t)ROWS * 3 * Wp),
        tail(4 * VL) {}

  float* xrow(int ch, int which, int row) { return xy.p + (((size_t)ch * 2 + which) * RING + row % RING) * Wp; }
  float* mrow(int row) { return mask.p + (size_t)(row % RING) * Wp; }
  double* vrow_d(int q, int map) { return reinterpret_cast<double*>(v.p + (size_t)q * 6 * Wp) + (size_t)map * Wp; }
  float* vrow_f(int q, int map) { return v.p + ((size_t)q * 6 + 4 + map) * Wp; }
  float* urow(int ch, int row, int map) {  // row >= -10
    return u.p + (((size_t)ch * RING + (row + RING) % RING) * 3 + map) * Wp;
  }
  float* grow(int q, int ch) { return grad.p + ((size_t)q * 3 + ch) * Wp; }

  void load_row(int q);
  template <int N> void vertical(int ch, int r, int count);
  vd horizontal_and_seeds(int q, int count);
  void adjoint_horizontal(int ch, int r);
  void forward_rows(int r, int n, double* sums);
  void clear_u(int r);
  template <int N> void emit_colour(int i, double* l1);
  double emit_depth(int i, int q);
  void run(int i0, int i1);
};

// Input row q -> ring slot q % K: mask, and x = c m, y = I m per channel (torch multiplies by
// the mask too, so NaN and inf propagate as in the reference).
void Band::load_row(int q) {
  const int W = P.W;
  const float* c = P.color + (size_t)q * W * 3;
  const float* I = P.image + (size_t)q * W * 3;
  const float* D = P.obs + (size_t)q * W;
  float* m = mrow(q);
  for (int j = 0; j < W; ++j) m[j] = P.has_depth ? (D[j] > 0.f ? 1.f : 0.f) : 1.f;
  float *x[3], *y[3];
  for (int ch = 0; ch < 3; ++ch) {
    x[ch] = xrow(ch, 0, q);
    y[ch] = xrow(ch, 1, q);
  }
  const int full = W / VL * VL;
  for (int j = 0; j < full; j += VL) {
    vf cv[3], iv[3];
    deinterleave3(c + 3 * j, cv);
    deinterleave3(I + 3 * j, iv);
    const vf mv = loadu(m + j);
    for (int ch = 0; ch < 3; ++ch) {
      storeu(x[ch] + j, cv[ch] * mv);
      storeu(y[ch] + j, iv[ch] * mv);
    }
  }
  for (int j = full; j < W; ++j) {
    for (int ch = 0; ch < 3; ++ch) {
      x[ch][j] = c[3 * j + ch] * m[j];
      y[ch][j] = I[3 * j + ch] * m[j];
    }
  }
}

// The vertical pass of map rows r..r+N-1, channel ch (input rows r..r+N+9), `count` vectors of
// 16 columns: F s and F s^2 in double (s = x + y and s^2 are exact there), F t and F t^2 in
// float. The rows share their input rows' loads; each row's arithmetic is the same for any N.
template <int N>
void Band::vertical(int ch, int r, int count) {
  constexpr int NR = K + N - 1;
  const float* xs[NR];
  const float* ys[NR];
  for (int t = 0; t < NR; ++t) {
    xs[t] = xrow(ch, 0, r + t);
    ys[t] = xrow(ch, 1, r + t);
  }
  for (int b = 0; b < count; ++b) {
    const int j = b * VL;
    vf t16[NR];
    for (int t = 0; t < NR; ++t) t16[t] = loadu(xs[t] + j) - loadu(ys[t] + j);
    for (int q = 0; q < N; ++q) {
      storeu(vrow_f(q, 0) + j, sym_filter(P.gf, [&](int t) { return t16[q + t]; }));
      storeu(vrow_f(q, 1) + j, sym_filter_squares(P.gf, t16 + q));
    }
    for (int h = 0; h < VL; h += VD) {
      vd s8[NR];
      for (int t = 0; t < NR; ++t) s8[t] = ld8(xs[t] + j + h) + ld8(ys[t] + j + h);
      for (int q = 0; q < N; ++q) {
        storeu(vrow_d(q, 0) + j + h, sym_filter(P.gd, [&](int t) { return s8[q + t]; }));
        storeu(vrow_d(q, 1) + j + h, sym_filter_squares(P.gd, s8 + q));
      }
    }
  }
}

// The horizontal pass of the maps of row q (of the rows computed together), then per map pixel S and (with gradients) the seeds a_mu,
// a_e, a_d times k_s (0 outside the map), in float: Var s = F s^2 - (F s)^2 is formed in double,
// after which no step cancels (see the header). Returns sum S (double).
vd Band::horizontal_and_seeds(int q, int count) {
  const vf ks = vf1(P.k_s), c1 = vf1((float)C1), c2 = vf1((float)C2);
  const double *fs = vrow_d(q, 0), *fss = vrow_d(q, 1);
  const float *ft = vrow_f(q, 0), *ftt = vrow_f(q, 1);
  float* sd[3];
  for (int k = 0; k < 3; ++k) sd[k] = seed.p + (size_t)k * SL + VL;
  vd total = vd{};
  for (int b = 0; b < count; ++b) {
    const int j = b * VL;
    vd ms[2], vs[2];
    for (int h = 0; h < 2; ++h) {
      ms[h] = row_filter(P.gd, fs + j + h * VD);
      vs[h] = row_filter(P.gd, fss + j + h * VD) - ms[h] * ms[h];
    }
    const vf Ms = narrow(ms[0], ms[1]), var_s = narrow(vs[0], vs[1]);  // mean and variance of s
    const vf Mt = row_filter(P.gf, ft + j);                           // mean of t = mu1 - mu2
    const vf var_t = row_filter(P.gf, ftt + j) - Mt * Mt;            // variance of t: B2 - A2
    const vf mu1 = 0.5f * (Ms + Mt), mu2 = 0.5f * (Ms - Mt);
    const vf B1 = 0.5f * vfma(Ms, Ms, Mt * Mt) + c1, A1 = 0.5f * (Ms * Ms - Mt * Mt) + c1;
    const vf B2 = 0.5f * (var_s + var_t) + c2;
    const vf rB1 = 1.f / B1, rB2 = 1.f / B2;
    const vf l = A1 * rB1, cs = (B2 - var_t) * rB2;
    vf S = l * cs;
    vf a[3] = {};
    if (P.grads) {
      // mu2 - mu1 l = -t (mu2 s + C1) / B1,  mu2 - mu1 cs = -t + mu1 var_t / B2: no cancellation
      const vf d_l = -(Mt * vfma(mu2, Ms, c1)) * rB1, d_cs = vfma(mu1 * var_t, rB2, -Mt);
      a[0] = ks * (2.f * (cs * d_l * rB1 - l * d_cs * rB2));
      a[1] = ks * (l * var_t * (rB2 * rB2));
      a[2] = ks * -(l * rB2);
    }
    if (j + VL > P.Wv) {  // the last vector: lanes past the map count for nothing
      const vi keep = (LANE + j) < P.Wv;
      S = select(keep, S, vf{});
      for (vf& ak : a) ak = select(keep, ak, vf{});
    }
    add_wide(total, S);
    if (P.grads)
      for (int k = 0; k < 3; ++k) storeu(sd[k] + j, a[k]);
  }
  return total;
}

// The seeds' full correlation along the row into the u ring (row r, channel ch):
// u[j] = sum_t g[t] a[j - t] = sum_t g[t] a[j - 10 + t] (symmetric taps); a is stored at
// offset VL with zeros around.
void Band::adjoint_horizontal(int ch, int r) {
  const int count = round_up(P.W, VL) / VL;
  for (int k = 0; k < 3; ++k) {
    float* out = urow(ch, r, k);
    const float* a = seed.p + (size_t)k * SL;  // a + 6 + t = the seed row at offset t - 10
    for (int b = 0; b < count; ++b) {
      const int j = b * VL;
      storeu(out + j, row_filter6(P.gf, a + j));
    }
  }
}

// Map row r (< Hv), every channel: S summed over the row, and the u ring's row r.
// Map rows r..r+n-1 (< Hv, n <= ROWS), every channel: S summed over each row (sums[q]), and
// the u ring's rows.
void Band::forward_rows(int r, int n, double* sums) {
  const int count = round_up(P.Wv, VL) / VL;  // vectors of map columns
  vd total[ROWS] = {};
  for (int ch = 0; ch < 3; ++ch) {
    // the horizontal pass reads up to 10 columns further: one more vector
    with_rows(n, [&](auto N) { vertical<N()>(ch, r, count + 1); });
    for (int q = 0; q < n; ++q) {
      total[q] += horizontal_and_seeds(q, count);
      if (P.grads) adjoint_horizontal(ch, r + q);
    }
  }
  for (int q = 0; q < n; ++q) sums[q] = hsum(total[q]);
}

// A ring slot for a map row outside the map (r >= Hv): no contribution.
void Band::clear_u(int r) {
  for (int ch = 0; ch < 3; ++ch)
    for (int k = 0; k < 3; ++k) std::fill_n(urow(ch, r, k), Wp, 0.f);
}

// Input rows i..i+N-1, colour: their L1 sums (l1[q]) and (with gradients) their colour
// gradients. The SSIM part needs the u ring rows i-10..i+N-1 (rows outside the map are zero
// slots); the rows share those loads.
template <int N>
void Band::emit_colour(int i, double* l1_sums) {
  constexpr int NR = K + N - 1;
  const int nv = round_up(P.W, VL) / VL;
  const vf kl1 = vf1(P.k_l1);
  vd l1[N] = {};
  for (int ch = 0; ch < 3; ++ch) {
    const float *x[N], *y[N], *m[N];
    for (int q = 0; q < N; ++q) {
      x[q] = xrow(ch, 0, i + q);
      y[q] = xrow(ch, 1, i + q);
      m[q] = mrow(i + q);
    }
    const float* us[3][NR];  // us[k][p]: row i - 10 + p
    if (P.do_ssim && P.grads)
      for (int k = 0; k < 3; ++k)
        for (int p = 0; p < NR; ++p) us[k][p] = urow(ch, i - R + p, k);
    for (int b = 0; b < nv; ++b) {
      const int j = b * VL;
      vf T[N][3] = {};
      if (P.do_ssim && P.grads) {
        for (int k = 0; k < 3; ++k) {
          vf uv[NR];
          for (int p = 0; p < NR; ++p) uv[p] = loadu(us[k][p] + j);
          for (int q = 0; q < N; ++q) T[q][k] = sym_filter(P.gf, [&](int t) { return uv[R + q - t]; });
        }
      }
      for (int q = 0; q < N; ++q) {
        // |c - I| m = |x - y| for m in {0, 1} (padding: 0 - 0)
        const vf xv = loadu(x[q] + j), diff = xv - loadu(y[q] + j);
        add_wide(l1[q], vabs(diff));
        if (!P.grads) continue;
        vf gr = kl1 * sign(diff);
        if (P.do_ssim) gr += vfma(2.f * diff, T[q][2], vfma(2.f * xv, T[q][1], T[q][0]));
        storeu(grow(q, ch) + j, gr * loadu(m[q] + j));
      }
    }
  }
  for (int q = 0; q < N; ++q) l1_sums[q] = hsum(l1[q]);
}

// Input row i (the q-th of the rows just emitted): its colour gradient interleaved into the
// output, and its depth term and gradient. Returns the row's sum |d - D| m.
double Band::emit_depth(int i, int q) {
  const int W = P.W;
  if (P.grads) {
    float* gc = P.grad_color + (size_t)i * W * 3;
    const float* gp[3] = {grow(q, 0), grow(q, 1), grow(q, 2)};
    const int full = W / VL * VL;
    for (int j = 0; j < full; j += VL) {
      const vf g3[3] = {loadu(gp[0] + j), loadu(gp[1] + j), loadu(gp[2] + j)};
      interleave3(g3, gc + 3 * j);
    }
    for (int j = full; j < W; ++j)
      for (int ch = 0; ch < 3; ++ch) gc[3 * j + ch] = gp[ch][j];
  }
  if (!P.has_depth) {
    if (P.grads) std::fill_n(P.grad_depth + (size_t)i * W, W, 0.f);
    return 0.0;
  }
  const float* m = mrow(i);
  const float* d = P.depth + (size_t)i * W;
  const float* D = P.obs + (size_t)i * W;
  float* gd = P.grads ? P.grad_depth + (size_t)i * W : nullptr;
  float* tl = tail.p;
  const vf kd = vf1(P.k_d);
  vd dep = vd{};
  for (int j = 0; j < W; j += VL) {
    const int n = std::min(VL, W - j);
    vf dv, Dv;
    if (n == VL) {
      dv = loadu(d + j);
      Dv = loadu(D + j);
    } else {  // the last partial vector, zero-padded (adds 0 to the sum)
      std::fill_n(tl, 2 * VL, 0.f);
      std::copy_n(d + j, n, tl);
      std::copy_n(D + j, n, tl + VL);
      dv = loadu(tl);
      Dv = loadu(tl + VL);
    }
    const vf mv = loadu(m + j), diff = dv - Dv;
    add_wide(dep, vabs(diff) * mv);
    if (gd) {
      const vf gv = kd * sign(diff) * mv;
      if (n == VL) {
        storeu(gd + j, gv);
      } else {
        storeu(tl + 2 * VL, gv);
        std::copy_n(tl + 2 * VL, n, gd + j);
      }
    }
  }
  return hsum(dep);
}

// Input rows [i0, i1), ROWS at a time: with SSIM, map rows from i0 - 10 (the halo) to
// min(i1, Hv) - 1.
void Band::run(int i0, int i1) {
  const int rs = P.do_ssim ? std::max(0, i0 - R) : i0;
  if (P.do_ssim)
    for (int q = rs; q < std::min(P.H, rs + R); ++q) load_row(q);
  for (int r = rs; r < i1; r += ROWS) {
    const int n = std::min(ROWS, i1 - r);
    if (P.do_ssim) {
      for (int q = 0; q < n; ++q)
        if (r + R + q < P.H) load_row(r + R + q);
      const int nf = std::max(0, std::min(n, P.Hv - r));  // map rows among r..r+n-1
      if (nf > 0) {
        double sums[ROWS];
        forward_rows(r, nf, sums);
        for (int q = 0; q < nf; ++q)
          if (r + q >= i0) P.row_ssim[r + q] = sums[q];
      }
      if (P.grads)
        for (int q = nf; q < n; ++q) clear_u(r + q);
    } else {
      for (int q = 0; q < n; ++q) load_row(r + q);
    }
    const int first = std::max(r, i0);  // rows before i0 are the halo
    double l1[ROWS];
    with_rows(r + n - first, [&](auto N) { emit_colour<N()>(first, l1); });
    for (int i = first; i < r + n; ++i) {
      P.row_l1[i] = l1[i - first];
      P.row_depth[i] = emit_depth(i, i - first);
    }
  }
}

void write_error(char* err, int errlen, const char* msg) {
  if (err && errlen > 0) {
    std::strncpy(err, msg, (size_t)errlen - 1);
    err[errlen - 1] = '\0';
  }
}

}  // namespace

extern "C" {

int slk_abi_version() { return ABI_VERSION; }

// The loss and, where grad_color / grad_depth are not null, its gradients w.r.t. the rendered
// colour (H,W,3) and depth (H,W). Inputs: contiguous float32; window: the 11 SSIM taps. out:
// loss, L1, SSIM (NaN when w_ssim is 0), depth term (0 without depth), n (valid pixels).
// Returns 0, or -1 with a message in err.
int slk_rgbd_loss(int H, int W, const float* color, const float* depth, const float* image, const float* obs,
                  const float* window, double w_l1, double w_ssim, double w_depth, double depth_unit, int nthreads,
                  float* grad_color, float* grad_depth, double* out, char* err, int errlen) {
  try {
    if (H < K || W < K) throw std::invalid_argument("image smaller than the 11x11 SSIM window");
    Problem P;
    P.H = H;
    P.W = W;
    P.Hv = H - R;
    P.Wv = W - R;
    P.Wp = round_up(W, VL) + 2 * VL;
    for (int t = 0; t < K; ++t)
      if (window[t] != window[K - 1 - t] || !(window[t] > 0.f)) throw std::invalid_argument("the SSIM window must be positive and symmetric");
    for (int t = 0; t <= K / 2; ++t) {
      P.gf[t] = vf1(window[t]);
      P.gd[t] = vd1(window[t]);
    }
    P.color = color;
    P.depth = depth;
    P.image = image;
    P.obs = obs;
    int64_t n = 0;
    for (int64_t p = 0; p < (int64_t)H * W; ++p) n += obs[p] > 0.f;
    P.has_depth = n > 0;
    if (!P.has_depth) n = (int64_t)H * W;
    P.do_ssim = w_ssim != 0.0;
    P.grads = grad_color != nullptr && grad_depth != nullptr;
    P.k_l1 = (float)(w_l1 / (3.0 * (double)n));
    P.k_d = P.has_depth ? (float)(w_depth / ((double)n * depth_unit)) : 0.f;
    const double map_size = 3.0 * P.Hv * P.Wv;
    P.k_s = (float)(-w_ssim / map_size);
    P.grad_color = grad_color;
    P.grad_depth = grad_depth;
    std::vector<double> rows((size_t)3 * H, 0.0);
    P.row_l1 = rows.data();
    P.row_depth = rows.data() + H;
    P.row_ssim = rows.data() + 2 * H;

    // one band per thread, handed out dynamically: a worker that is not scheduled in time
    // (a busy machine) is not waited for, the caller computes its band too
    const int bands = std::max(1, std::min(nthreads, H / K));
    Pool::instance().run(bands, bands, [&](int64_t b, int) {
      Band band(P);
      band.run((int)((int64_t)H * b / bands), (int)((int64_t)H * (b + 1) / bands));
    });

    double l1 = 0, dep = 0, ssim = 0;
    for (int i = 0; i < H; ++i) {
      l1 += P.row_l1[i];
      dep += P.row_depth[i];
    }
    for (int r = 0; r < P.Hv; ++r) ssim += P.row_ssim[r];
    l1 /= 3.0 * (double)n;
    dep = P.has_depth ? dep / (double)n / depth_unit : 0.0;
    ssim = P.do_ssim ? ssim / map_size : NAN;
    out[0] = w_l1 * l1 + (P.do_ssim ? w_ssim * (1.0 - ssim) : 0.0) + (P.has_depth ? w_depth * dep : 0.0);
    out[1] = l1;
    out[2] = ssim;
    out[3] = dep;
    out[4] = (double)n;
    return 0;
  } catch (const std::exception& e) {
    write_error(err, errlen, e.what());
  } catch (...) {
    write_error(err, errlen, "unknown error");
  }
  return -1;
}

}  // extern "C"
