// slamkit fused RGB-D mapping loss: value and gradients in one pass, no autograd graph.
//
// Plain C++17 with a C ABI (loaded with ctypes by slamkit_plugins/losses/fused_rgbd_loss.py,
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
// SSIM backward, per channel with x = c m, y = I m and F the valid separable filter: the map
// S = l cs depends on x through mu1 = F x, e11 = F(x x), e12 = F(x y); with the per-pixel
// adjoints a_mu = dS/dmu1, a_11 = dS/de11, a_12 = dS/de12 (scaled by -w_ssim / #map),
//   dloss/dx = F^T a_mu + 2 x F^T a_11 + y F^T a_12,
// where F^T, the adjoint of a valid correlation, is the full correlation with the same taps
// (zero outside the map).
//
// Layout: row bands (one per thread). Each band streams its rows: deinterleave an input row
// into planar, masked channel rows (a ring of 11), filter vertically then horizontally (the 5
// maps mu1, mu2, e11, e22, e12 in one sweep over the 11 rows), compute S and its three
// adjoints, correlate those horizontally (a ring of 11 rows), and once an input row has all
// 11 contributions, correlate vertically and write its gradient. A band recomputes the 10 map
// rows above it (the halo its first rows' gradients need). Every output and every sum has a
// fixed order of operations, so results do not depend on the number of threads.
//
// Arithmetic: float32, 16 lanes per vector (GCC/Clang vector extensions: AVX-512 with
// -march=native, split into narrower registers elsewhere); separate multiplies and adds (no
// FMA), so the portable and the native build compute the same numbers. Sums over pixels are
// accumulated in double.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace {

constexpr int ABI_VERSION = 1;
constexpr int K = 11;      // SSIM window taps
constexpr int R = K - 1;   // rows / columns the valid filter loses
constexpr int VL = 16;     // floats per vector
constexpr float C1 = (float)(0.01 * 0.01);  // (K1 data_range)^2 as pytorch_msssim, rounded as torch does
constexpr float C2 = (float)(0.03 * 0.03);

typedef float vf __attribute__((vector_size(64)));
typedef float vf8 __attribute__((vector_size(32)));
typedef double vd __attribute__((vector_size(64)));
typedef int32_t vi __attribute__((vector_size(64)));

inline vf vf1(float x) { return vf{x, x, x, x, x, x, x, x, x, x, x, x, x, x, x, x}; }
inline vf ld(const float* p) {
  vf v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
inline void st(float* p, vf v) { std::memcpy(p, &v, sizeof v); }
inline vf select(vi m, vf a, vf b) { return (vf)(((vi)a & m) | ((vi)b & ~m)); }
// sign(v) as torch's abs backward: 0 at 0, NaN for NaN
inline vf sign(vf v) { return select(v > 0, vf1(1.f), select(v < 0, vf1(-1.f), v)); }
inline vf vabs(vf v) { return (vf)((vi)v & (vi{} + 0x7fffffff)); }
// a += v, the 16 floats widened to double (low and high halves added first: a fixed order)
inline void add_wide(vd& a, vf v) {
  vf8 lo, hi;
  std::memcpy(&lo, &v, sizeof lo);
  std::memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof lo, sizeof hi);
  a += __builtin_convertvector(lo, vd) + __builtin_convertvector(hi, vd);
}
inline double hsum(vd a) {
  double h[8];
  std::memcpy(h, &a, sizeof h);
  return ((h[0] + h[4]) + (h[1] + h[5])) + ((h[2] + h[6]) + (h[3] + h[7]));
}
inline int round_up(int x, int m) { return (x + m - 1) / m * m; }

// The whole problem, shared by the bands (read-only but for each band's own output rows).
struct Problem {
  int H, W, Hv, Wv;
  int Wp;  // padded planar row length (floats): covers the filters' reads past the last vector
  const float *color, *depth, *image, *obs;
  float g[K];
  bool has_depth, do_ssim, grads;
  float k_l1, k_d, k_s;  // gradient scales: w_l1 / 3n, w_depth / (n unit), -w_ssim / (3 Hv Wv)
  float* grad_color;     // (H,W,3) or null
  float* grad_depth;     // (H,W) or null
  double *row_l1, *row_depth, *row_ssim;  // per-row sums (H, H, Hv)
};

// One band's rings and row buffers (zero-initialised: the padding stays zero).
struct Band {
  const Problem& P;
  std::vector<float> xy;    // [channel][x or y][ring slot][Wp]: c m and I m, planar
  std::vector<float> mask;  // [ring slot][Wp]
  std::vector<float> v;     // [5][Wp]: the vertical pass of mu1, mu2, e11, e22, e12
  std::vector<float> seed;  // [3][Wp + 2 VL]: a_mu, a_11, a_12 of one map row at offset R, zero around
  std::vector<float> u;     // [channel][ring slot][3][Wp]: the seeds correlated horizontally
  std::vector<float> grad;  // [3][Wp]: one row's colour gradient, planar
  std::vector<float> tail;  // [4 VL]: the last partial vector of an unpadded row
  int seed_len;

  explicit Band(const Problem& p) : P(p), seed_len(p.Wp + 2 * VL) {
    xy.assign((size_t)3 * 2 * K * P.Wp, 0.f);
    mask.assign((size_t)K * P.Wp, 0.f);
    v.assign((size_t)5 * P.Wp, 0.f);
    seed.assign((size_t)3 * seed_len, 0.f);
    u.assign((size_t)3 * K * 3 * P.Wp, 0.f);
    grad.assign((size_t)3 * P.Wp, 0.f);
    tail.assign(4 * VL, 0.f);
  }

  float* xrow(int ch, int which, int row) { return &xy[(((size_t)ch * 2 + which) * K + row % K) * P.Wp]; }
  float* mrow(int row) { return &mask[(size_t)(row % K) * P.Wp]; }
  float* urow(int ch, int row, int map) { return &u[(((size_t)ch * K + (row + K) % K) * 3 + map) * P.Wp]; }

  void load_row(int q);
  double forward_row(int r);
  void clear_u(int r);
  void emit_row(int i, double& l1, double& dep);
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
  for (int ch = 0; ch < 3; ++ch) {
    float* x = xrow(ch, 0, q);
    float* y = xrow(ch, 1, q);
    for (int j = 0; j < W; ++j) {
      x[j] = c[3 * j + ch] * m[j];
      y[j] = I[3 * j + ch] * m[j];
    }
  }
}

// Map row r (< Hv): the five filtered maps, S, and (with gradients) the seeds correlated
// horizontally into the u ring. Returns sum S over the row and the channels.
double Band::forward_row(int r) {
  const int nv_out = round_up(P.Wv, VL) / VL;  // vectors of map columns
  const int nv_in = nv_out + 1;                 // vertical-pass vectors the horizontal pass reads
  const int nv_adj = round_up(P.W, VL) / VL;
  const float* g = P.g;
  vd total = vd{};
  for (int ch = 0; ch < 3; ++ch) {
    const float* xs[K];
    const float* ys[K];
    for (int t = 0; t < K; ++t) {
      xs[t] = xrow(ch, 0, r + t);
      ys[t] = xrow(ch, 1, r + t);
    }
    float* vm[5];
    for (int k = 0; k < 5; ++k) vm[k] = &v[(size_t)k * P.Wp];
    for (int b = 0; b < nv_in; ++b) {
      const int j = b * VL;
      vf a0 = vf{}, a1 = vf{}, a2 = vf{}, a3 = vf{}, a4 = vf{};
      for (int t = 0; t < K; ++t) {
        const vf x = ld(xs[t] + j), y = ld(ys[t] + j), w = vf1(g[t]);
        a0 += w * x;
        a1 += w * y;
        a2 += w * (x * x);
        a3 += w * (y * y);
        a4 += w * (x * y);
      }
      st(vm[0] + j, a0);
      st(vm[1] + j, a1);
      st(vm[2] + j, a2);
      st(vm[3] + j, a3);
      st(vm[4] + j, a4);
    }
    float* sd[3];
    for (int k = 0; k < 3; ++k) sd[k] = &seed[(size_t)k * seed_len];
    const vf ks = vf1(P.k_s);
    for (int b = 0; b < nv_out; ++b) {
      const int j = b * VL;
      vf f[5];
      for (int k = 0; k < 5; ++k) {
        vf a = vf{};
        for (int t = 0; t < K; ++t) a += vf1(g[t]) * ld(vm[k] + j + t);
        f[k] = a;
      }
      const vf mu1 = f[0], mu2 = f[1];
      const vf mu1s = mu1 * mu1, mu2s = mu2 * mu2, mu12 = mu1 * mu2;
      const vf s11 = f[2] - mu1s, s22 = f[3] - mu2s, s12 = f[4] - mu12;
      const vf B1 = (mu1s + mu2s) + C1, B2 = (s11 + s22) + C2;
      const vf cs = (2.f * s12 + C2) / B2;
      const vf l = (2.f * mu12 + C1) / B1;
      const vf S = l * cs;
      vi lane = vi{0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15} + j;
      const vi keep = lane < P.Wv;
      add_wide(total, select(keep, S, vf{}));
      if (P.grads) {
        const vf rB2 = 1.f / B2;
        const vf a12 = 2.f * l * rB2;
        const vf a11 = -(S * rB2);
        const vf amu = (2.f * cs) * (mu2 - mu1 * l) / B1 - mu2 * a12 - 2.f * mu1 * a11;
        st(sd[0] + R + j, select(keep, ks * amu, vf{}));
        st(sd[1] + R + j, select(keep, ks * a11, vf{}));
        st(sd[2] + R + j, select(keep, ks * a12, vf{}));
      }
    }
    if (P.grads) {
      // full correlation: u[j] = sum_t g[t] a[j - t], a stored at offset R (zeros around)
      for (int k = 0; k < 3; ++k) {
        float* out = urow(ch, r, k);
        for (int b = 0; b < nv_adj; ++b) {
          const int j = b * VL;
          vf a = vf{};
          for (int t = 0; t < K; ++t) a += vf1(g[t]) * ld(sd[k] + j + R - t);
          st(out + j, a);
        }
      }
    }
  }
  return hsum(total);
}

// A ring slot for a map row outside the map (r >= Hv): no contribution.
void Band::clear_u(int r) {
  for (int ch = 0; ch < 3; ++ch)
    for (int k = 0; k < 3; ++k) std::fill_n(urow(ch, r, k), P.Wp, 0.f);
}

// Input row i: its L1 and depth sums, and (with gradients) its colour and depth gradients. The
// SSIM part needs the u ring rows i-10..i (rows outside the map are zero slots).
void Band::emit_row(int i, double& l1_sum, double& dep_sum) {
  const int W = P.W, nv = round_up(W, VL) / VL;
  const float* g = P.g;
  const vf kl1 = vf1(P.k_l1);
  vd l1 = vd{};
  const float* m = mrow(i);
  for (int ch = 0; ch < 3; ++ch) {
    const float* x = xrow(ch, 0, i);
    const float* y = xrow(ch, 1, i);
    float* out = &grad[(size_t)ch * P.Wp];
    const float* us[3][K];
    if (P.do_ssim && P.grads)
      for (int k = 0; k < 3; ++k)
        for (int t = 0; t < K; ++t) us[k][t] = urow(ch, i - t, k);
    for (int b = 0; b < nv; ++b) {
      const int j = b * VL;
      // |c - I| m = |x - y| for m in {0, 1} (padding: 0 - 0)
      const vf xv = ld(x + j), yv = ld(y + j), diff = xv - yv;
      add_wide(l1, vabs(diff));
      if (!P.grads) continue;
      vf gr = kl1 * sign(diff);
      if (P.do_ssim) {
        vf T[3];
        for (int k = 0; k < 3; ++k) {
          vf a = vf{};
          for (int t = 0; t < K; ++t) a += vf1(g[t]) * ld(us[k][t] + j);
          T[k] = a;
        }
        gr += T[0] + 2.f * xv * T[1] + yv * T[2];
      }
      st(out + j, gr * ld(m + j));
    }
  }
  l1_sum = hsum(l1);
  if (P.grads) {
    float* gc = P.grad_color + (size_t)i * W * 3;
    for (int j = 0; j < W; ++j)
      for (int ch = 0; ch < 3; ++ch) gc[3 * j + ch] = grad[(size_t)ch * P.Wp + j];
  }
  dep_sum = 0.0;
  if (!P.has_depth) {
    if (P.grads) std::fill_n(P.grad_depth + (size_t)i * W, W, 0.f);
    return;
  }
  const float* d = P.depth + (size_t)i * W;
  const float* D = P.obs + (size_t)i * W;
  float* gd = P.grad_depth ? P.grad_depth + (size_t)i * W : nullptr;
  const vf kd = vf1(P.k_d);
  vd dep = vd{};
  for (int j = 0; j < W; j += VL) {
    const int n = std::min(VL, W - j);
    vf dv, Dv;
    if (n == VL) {
      dv = ld(d + j);
      Dv = ld(D + j);
    } else {  // the last partial vector, zero-padded (adds 0 to the sum)
      std::fill(tail.begin(), tail.end(), 0.f);
      std::copy_n(d + j, n, tail.data());
      std::copy_n(D + j, n, tail.data() + VL);
      dv = ld(tail.data());
      Dv = ld(tail.data() + VL);
    }
    const vf mv = ld(m + j), diff = dv - Dv;
    add_wide(dep, vabs(diff) * mv);
    if (gd) {
      const vf gv = kd * sign(diff) * mv;
      if (n == VL) {
        st(gd + j, gv);
      } else {
        st(tail.data() + 2 * VL, gv);
        std::copy_n(tail.data() + 2 * VL, n, gd + j);
      }
    }
  }
  dep_sum = hsum(dep);
}

// Input rows [i0, i1): with SSIM, map rows from i0 - 10 (the halo) to min(i1, Hv) - 1.
void Band::run(int i0, int i1) {
  const int rs = P.do_ssim ? std::max(0, i0 - R) : i0;
  if (P.do_ssim)
    for (int q = rs; q < std::min(P.H, rs + R); ++q) load_row(q);
  for (int r = rs; r < i1; ++r) {
    if (P.do_ssim) {
      if (r + R < P.H) load_row(r + R);
      if (r < P.Hv) {
        const double s = forward_row(r);
        if (r >= i0) P.row_ssim[r] = s;
      } else if (P.grads) {
        clear_u(r);
      }
    } else {
      load_row(r);
    }
    if (r >= i0) emit_row(r, P.row_l1[r], P.row_depth[r]);
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
    P.color = color;
    P.depth = depth;
    P.image = image;
    P.obs = obs;
    std::copy_n(window, K, P.g);
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

    const int bands = std::max(1, std::min(nthreads, H / K));
    std::vector<std::exception_ptr> errors(bands);
    auto work = [&](int b) {
      try {
        Band band(P);
        band.run((int)((int64_t)H * b / bands), (int)((int64_t)H * (b + 1) / bands));
      } catch (...) {
        errors[b] = std::current_exception();
      }
    };
    std::vector<std::thread> threads;
    for (int b = 1; b < bands; ++b) threads.emplace_back(work, b);
    work(0);
    for (auto& t : threads) t.join();
    for (auto& e : errors)
      if (e) std::rethrow_exception(e);

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
