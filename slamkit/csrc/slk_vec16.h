// 64-byte vectors for slamkit's compiled kernels: 16 float32 / int32 lanes (vf, vi: a 16-pixel
// tile row is one vector) and 8 float64 lanes (vd): one AVX-512 register where the target has
// it, else a pair of 32-byte vectors (AVX2 registers with -march=native on most laptops and on
// AMD CPUs before Zen 4).
//
// Why not one 64-byte GCC vector everywhere: without AVX-512, GCC lowers 64-byte vector code
// through memory, lane by lane, with a branch per lane for every compare. Measured on a 2-core
// AVX2 Zen 2: the rasteriser's forward + backward 7x the cycles per pair of the same code on an
// AVX-512 machine; with the pair of 8-lane vectors, see docs/cpu_rasterizer.md.
//
// Both variants offer the same interface: arithmetic and comparisons with vectors and scalars,
// lane access v[i], vf1 / vi1 / vd1 (broadcast), as_vi / as_vf (bit casts), to_vi / to_vf (value
// conversions, truncating toward zero), select, any, all, lane_bits (of masks: lanes 0 or -1,
// as comparisons give; other values, which no kernel passes, act differently per variant: a
// block's select reads only the sign bit with AVX), hsum, vfma, vsqrt, LANE (0..15), and
// for vd: ld8 / st8 (8 floats widened / rounded), widen / narrow (one vf <-> two vd). Arithmetic
// is IEEE lane by lane in both: without -ffp-contract, results are the same bits, except the
// float hsum's order of additions and vfma (fused where the target has FMA: AVX-512, and AVX2
// CPUs with FMA, which all have it; a portable build rounds the product and the sum apart). vblock / iblock:
// what a kernel processes at once, HALVES per vector (one with AVX-512, else the two halves: the
// rasteriser's blocks), with block(v, h), block_of (broadcast) and block_lanes (0..7 or 0..15),
// and the same select / any / all / lane_bits. loadu / storeu:
// unaligned loads and stores (a memcpy of the pair would go through 16-byte pieces and stall
// the 32-byte loads that read them back).
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>

#if defined(__AVX512F__) || defined(__AVX__)
#include <immintrin.h>
#endif

namespace {

#if defined(__AVX512F__)

typedef float vf __attribute__((vector_size(64)));
typedef int32_t vi __attribute__((vector_size(64)));

const vi LANE = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15};

inline vf vf1(float x) { return (vf)_mm512_set1_ps(x); }  // (0 + x is not x for x = -0)
inline vi as_vi(vf x) { return (vi)x; }
inline vf as_vf(vi x) { return (vf)x; }
inline vi to_vi(vf x) { return __builtin_convertvector(x, vi); }
inline vf to_vf(vi x) { return __builtin_convertvector(x, vf); }
inline bool any(vi m) { return _mm512_test_epi32_mask((__m512i)m, (__m512i)m) != 0; }
inline bool all(vi m) { return _mm512_test_epi32_mask((__m512i)m, (__m512i)m) == 0xFFFF; }
inline uint32_t lane_bits(vi m) { return _mm512_test_epi32_mask((__m512i)m, (__m512i)m); }
inline float hsum(vf v) { return _mm512_reduce_add_ps((__m512)v); }
inline vf vfma(vf a, vf b, vf c) { return (vf)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c); }
inline vf vsqrt(vf x) { return (vf)_mm512_sqrt_ps((__m512)x); }
// the whole vector is one block (see the pair variant)
constexpr int HALVES = 1;
typedef vf vblock;
typedef vi iblock;
inline vf& block(vf& v, int) { return v; }
inline vi& block(vi& v, int) { return v; }
inline vf block_of(float x) { return vf1(x); }
inline vi block_lanes() { return LANE; }

typedef double vd __attribute__((vector_size(64)));
inline vd vd1(double x) { return (vd)_mm512_set1_pd(x); }
typedef float vf_u __attribute__((vector_size(64), aligned(4)));
typedef double vd_u __attribute__((vector_size(64), aligned(8)));
inline vf loadu(const float* p) { return *(const vf_u*)p; }
inline vd loadu(const double* p) { return *(const vd_u*)p; }
inline void storeu(float* p, vf v) { *(vf_u*)p = v; }
inline void storeu(double* p, vd v) { *(vd_u*)p = v; }
inline vd vfma(vd a, vd b, vd c) { return (vd)_mm512_fmadd_pd((__m512d)a, (__m512d)b, (__m512d)c); }
// 8 floats widened to double, 8 doubles rounded to float
inline vd ld8(const float* p) { return (vd)_mm512_cvtps_pd(_mm256_loadu_ps(p)); }
inline void st8(float* p, vd v) { _mm256_storeu_ps(p, _mm512_cvtpd_ps((__m512d)v)); }
// 16 floats <-> two vectors of 8 doubles, in registers
inline void widen(vf v, vd& lo, vd& hi) {
  lo = (vd)_mm512_cvtps_pd(_mm512_castps512_ps256((__m512)v));
  hi = (vd)_mm512_cvtps_pd(_mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd((__m512)v), 1)));
}
inline vf narrow(vd lo, vd hi) {
  const __m256 l = _mm512_cvtpd_ps((__m512d)lo), h = _mm512_cvtpd_ps((__m512d)hi);
  return (vf)_mm512_castpd_ps(_mm512_insertf64x4(_mm512_castpd256_pd512(_mm256_castps_pd(l)), _mm256_castps_pd(h), 1));
}
// ((h0 + h4) + (h1 + h5)) + ((h2 + h6) + (h3 + h7))
inline double hsum(vd a) {
  double h[8];
  std::memcpy(h, &a, sizeof h);
  return ((h[0] + h[4]) + (h[1] + h[5])) + ((h[2] + h[6]) + (h[3] + h[7]));
}

#else

typedef float f8 __attribute__((vector_size(32)));
typedef int32_t i8 __attribute__((vector_size(32)));
typedef double d4 __attribute__((vector_size(32)));

struct alignas(64) vf {
  f8 lo, hi;
  float& operator[](int i) { return reinterpret_cast<float*>(this)[i]; }  // vectors alias their lanes
  float operator[](int i) const { return reinterpret_cast<const float*>(this)[i]; }
};
struct alignas(64) vi {
  i8 lo, hi;
  int32_t& operator[](int i) { return reinterpret_cast<int32_t*>(this)[i]; }
  int32_t operator[](int i) const { return reinterpret_cast<const int32_t*>(this)[i]; }
};
struct alignas(64) vd {
  d4 lo, hi;
  double& operator[](int i) { return reinterpret_cast<double*>(this)[i]; }
  double operator[](int i) const { return reinterpret_cast<const double*>(this)[i]; }
};
static_assert(sizeof(vf) == 64 && sizeof(vi) == 64 && sizeof(vd) == 64, "no padding");

typedef float f8_u __attribute__((vector_size(32), aligned(4)));
typedef double d4_u __attribute__((vector_size(32), aligned(8)));
inline vf loadu(const float* p) { return vf{*(const f8_u*)p, *(const f8_u*)(p + 8)}; }
inline vd loadu(const double* p) { return vd{*(const d4_u*)p, *(const d4_u*)(p + 4)}; }
inline void storeu(float* p, vf v) {
  *(f8_u*)p = v.lo;
  *(f8_u*)(p + 8) = v.hi;
}
inline void storeu(double* p, vd v) {
  *(d4_u*)p = v.lo;
  *(d4_u*)(p + 4) = v.hi;
}

// element-wise operators on both halves; S: the scalar type a vector operand may be
#define SLK_V16_BINARY(V, S, R, OP)                                                        \
  inline R operator OP(V a, V b) { return R{a.lo OP b.lo, a.hi OP b.hi}; }                \
  inline R operator OP(V a, S b) { return R{a.lo OP b, a.hi OP b}; }                      \
  inline R operator OP(S a, V b) { return R{a OP b.lo, a OP b.hi}; }
#define SLK_V16_ASSIGN(V, S, OP)                                                           \
  inline V& operator OP##=(V& a, V b) { return a = a OP b; }                              \
  inline V& operator OP##=(V& a, S b) { return a = a OP b; }
SLK_V16_BINARY(vf, float, vf, +)
SLK_V16_BINARY(vf, float, vf, -)
SLK_V16_BINARY(vf, float, vf, *)
SLK_V16_BINARY(vf, float, vf, /)
SLK_V16_BINARY(vf, float, vi, <)
SLK_V16_BINARY(vf, float, vi, <=)
SLK_V16_BINARY(vf, float, vi, >)
SLK_V16_BINARY(vf, float, vi, >=)
SLK_V16_ASSIGN(vf, float, +)
SLK_V16_ASSIGN(vf, float, -)
SLK_V16_ASSIGN(vf, float, *)
SLK_V16_BINARY(vd, double, vd, +)
SLK_V16_BINARY(vd, double, vd, -)
SLK_V16_BINARY(vd, double, vd, *)
SLK_V16_BINARY(vd, double, vd, /)
SLK_V16_ASSIGN(vd, double, +)
SLK_V16_ASSIGN(vd, double, -)
SLK_V16_BINARY(vi, int32_t, vi, +)
SLK_V16_BINARY(vi, int32_t, vi, -)
SLK_V16_BINARY(vi, int32_t, vi, &)
SLK_V16_BINARY(vi, int32_t, vi, |)
SLK_V16_BINARY(vi, int32_t, vi, ^)
SLK_V16_BINARY(vi, int32_t, vi, <)
SLK_V16_BINARY(vi, int32_t, vi, <=)
SLK_V16_BINARY(vi, int32_t, vi, >)
SLK_V16_BINARY(vi, int32_t, vi, >=)
SLK_V16_BINARY(vi, int32_t, vi, ==)
SLK_V16_ASSIGN(vi, int32_t, +)
SLK_V16_ASSIGN(vi, int32_t, -)
SLK_V16_ASSIGN(vi, int32_t, &)
SLK_V16_ASSIGN(vi, int32_t, |)
#undef SLK_V16_BINARY
#undef SLK_V16_ASSIGN
inline vf operator-(vf a) { return vf{-a.lo, -a.hi}; }
inline vd operator-(vd a) { return vd{-a.lo, -a.hi}; }
inline vi operator~(vi a) { return vi{~a.lo, ~a.hi}; }
inline vi operator<<(vi a, int n) { return vi{a.lo << n, a.hi << n}; }

const vi LANE = {i8{0, 1, 2, 3, 4, 5, 6, 7}, i8{8, 9, 10, 11, 12, 13, 14, 15}};

inline vf vf1(float x) {
  const f8 h = {x, x, x, x, x, x, x, x};
  return vf{h, h};
}
inline vd vd1(double x) {
  const d4 h = {x, x, x, x};
  return vd{h, h};
}
inline vi as_vi(vf x) { return vi{(i8)x.lo, (i8)x.hi}; }
inline vf as_vf(vi x) { return vf{(f8)x.lo, (f8)x.hi}; }
inline vi to_vi(vf x) { return vi{__builtin_convertvector(x.lo, i8), __builtin_convertvector(x.hi, i8)}; }
inline vf to_vf(vi x) { return vf{__builtin_convertvector(x.lo, f8), __builtin_convertvector(x.hi, f8)}; }

#if defined(__AVX__)
inline float hsum(f8 v) {
  const __m128 s4 = _mm_add_ps(_mm256_castps256_ps128((__m256)v), _mm256_extractf128_ps((__m256)v, 1));
  const __m128 s2 = _mm_add_ps(s4, _mm_movehl_ps(s4, s4));
  return _mm_cvtss_f32(_mm_add_ss(s2, _mm_movehdup_ps(s2)));
}
inline float hsum(vf v) { return hsum(v.lo + v.hi); }
inline vf vsqrt(vf x) { return vf{(f8)_mm256_sqrt_ps((__m256)x.lo), (f8)_mm256_sqrt_ps((__m256)x.hi)}; }
inline vd ld8(const float* p) {
  return vd{(d4)_mm256_cvtps_pd(_mm_loadu_ps(p)), (d4)_mm256_cvtps_pd(_mm_loadu_ps(p + 4))};
}
inline void st8(float* p, vd v) {
  _mm_storeu_ps(p, _mm256_cvtpd_ps((__m256d)v.lo));
  _mm_storeu_ps(p + 4, _mm256_cvtpd_ps((__m256d)v.hi));
}
inline void widen(vf v, vd& lo, vd& hi) {
  const __m256 a = (__m256)v.lo, b = (__m256)v.hi;
  lo = vd{(d4)_mm256_cvtps_pd(_mm256_castps256_ps128(a)), (d4)_mm256_cvtps_pd(_mm256_extractf128_ps(a, 1))};
  hi = vd{(d4)_mm256_cvtps_pd(_mm256_castps256_ps128(b)), (d4)_mm256_cvtps_pd(_mm256_extractf128_ps(b, 1))};
}
inline vf narrow(vd lo, vd hi) {
  return vf{(f8)_mm256_set_m128(_mm256_cvtpd_ps((__m256d)lo.hi), _mm256_cvtpd_ps((__m256d)lo.lo)),
            (f8)_mm256_set_m128(_mm256_cvtpd_ps((__m256d)hi.hi), _mm256_cvtpd_ps((__m256d)hi.lo))};
}
#else
inline float hsum(f8 s8) { return ((s8[0] + s8[4]) + (s8[1] + s8[5])) + ((s8[2] + s8[6]) + (s8[3] + s8[7])); }
inline float hsum(vf v) { return hsum(v.lo + v.hi); }
inline vf vsqrt(vf x) {
  for (int i = 0; i < 16; ++i) x[i] = std::sqrt(x[i]);
  return x;
}
inline vd ld8(const float* p) {
  vd v;
  for (int i = 0; i < 8; ++i) v[i] = p[i];
  return v;
}
inline void st8(float* p, vd v) {
  for (int i = 0; i < 8; ++i) p[i] = (float)v[i];
}
inline void widen(vf v, vd& lo, vd& hi) {
  for (int i = 0; i < 8; ++i) {
    lo[i] = v[i];
    hi[i] = v[8 + i];
  }
}
inline vf narrow(vd lo, vd hi) {
  vf v;
  for (int i = 0; i < 8; ++i) {
    v[i] = (float)lo[i];
    v[8 + i] = (float)hi[i];
  }
  return v;
}
#endif

#if defined(__FMA__)
inline f8 vfma(f8 a, f8 b, f8 c) { return (f8)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c); }
inline vd vfma(vd a, vd b, vd c) {
  return vd{(d4)_mm256_fmadd_pd((__m256d)a.lo, (__m256d)b.lo, (__m256d)c.lo),
            (d4)_mm256_fmadd_pd((__m256d)a.hi, (__m256d)b.hi, (__m256d)c.hi)};
}
#else
inline f8 vfma(f8 a, f8 b, f8 c) { return a * b + c; }
inline vd vfma(vd a, vd b, vd c) { return a * b + c; }
#endif
inline vf vfma(vf a, vf b, vf c) { return vf{vfma(a.lo, b.lo, c.lo), vfma(a.hi, b.hi, c.hi)}; }
// ((h0 + h4) + (h1 + h5)) + ((h2 + h6) + (h3 + h7)), as the AVX-512 variant
inline double hsum(vd a) {
  const d4 s = a.lo + a.hi;
  return (s[0] + s[1]) + (s[2] + s[3]);
}

// One half (f8 / i8, an AVX2 register) on its own, for kernels that skip a half no work touches
// (`block`: half h of a vector, by reference; the rasteriser keeps arrays of halves instead): the
// same lane-by-lane arithmetic as the pair's.
constexpr int HALVES = 2;
typedef f8 vblock;
typedef i8 iblock;
inline f8& block(vf& v, int h) { return h ? v.hi : v.lo; }
inline i8& block(vi& v, int h) { return h ? v.hi : v.lo; }
inline f8 block_of(float x) { return f8{x, x, x, x, x, x, x, x}; }
inline i8 block_lanes() { return i8{0, 1, 2, 3, 4, 5, 6, 7}; }
inline i8 as_vi(f8 x) { return (i8)x; }
inline f8 as_vf(i8 x) { return (f8)x; }
inline f8 to_vf(i8 x) { return __builtin_convertvector(x, f8); }
#if defined(__AVX__)
// (one blend instead of and / andnot / or: a shorter chain where a select carries a loop's state)
inline f8 select(i8 m, f8 a, f8 b) { return (f8)_mm256_blendv_ps((__m256)b, (__m256)a, (__m256)m); }
inline i8 select(i8 m, i8 a, i8 b) { return (i8)_mm256_blendv_ps((__m256)b, (__m256)a, (__m256)m); }
#else
inline f8 select(i8 m, f8 a, f8 b) { return (f8)(((i8)a & m) | ((i8)b & ~m)); }
inline i8 select(i8 m, i8 a, i8 b) { return (a & m) | (b & ~m); }
#endif
#if defined(__AVX__)
inline bool any(i8 m) { return _mm256_movemask_ps((__m256)m) != 0; }
inline bool all(i8 m) { return _mm256_movemask_ps((__m256)m) == 0xFF; }
inline uint32_t lane_bits(i8 m) { return (uint32_t)_mm256_movemask_ps((__m256)m); }
#else
inline bool any(i8 m) {
  for (int i = 0; i < 8; ++i)
    if (m[i]) return true;
  return false;
}
inline bool all(i8 m) {
  for (int i = 0; i < 8; ++i)
    if (!m[i]) return false;
  return true;
}
inline uint32_t lane_bits(i8 m) {
  uint32_t bits = 0;
  for (int i = 0; i < 8; ++i) bits |= (uint32_t)(m[i] != 0) << i;
  return bits;
}
#endif
inline bool any(vi m) { return any(m.lo | m.hi); }
inline bool all(vi m) { return all(m.lo & m.hi); }
inline uint32_t lane_bits(vi m) { return lane_bits(m.lo) | lane_bits(m.hi) << 8; }

#endif  // AVX-512

inline vi vi1(int32_t x) { return vi{} + x; }
inline vf select(vi m, vf a, vf b) { return as_vf((as_vi(a) & m) | (as_vi(b) & ~m)); }
inline vi select(vi m, vi a, vi b) { return (a & m) | (b & ~m); }

}  // namespace
