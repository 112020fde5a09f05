// 16-lane float32 / int32 vectors for slamkit's compiled kernels (a 16-pixel tile row is one
// vector): one AVX-512 register where the target has it, else a pair of 8-lane vectors (AVX2
// registers with -march=native on most laptops and AMD CPUs before Zen 4).
//
// Why not one 64-byte GCC vector everywhere: without AVX-512, GCC lowers 64-byte vector code
// through memory, lane by lane, with a branch per lane for every compare. Measured on a 2-core
// AVX2 Zen 2: the rasteriser's forward + backward 7x the cycles per pair of the same code on an
// AVX-512 machine; with the pair of 8-lane vectors, see docs/cpu_rasterizer.md.
//
// Both variants offer the same interface: arithmetic and comparisons with vectors and scalars,
// lane access v[i], vf1 / vi1 (broadcast), as_vi / as_vf (bit casts), to_vi / to_vf (value
// conversions, truncating toward zero), select, any, all, hsum, vfma, vsqrt, and LANE (0..15).
// Arithmetic is IEEE float32 lane by lane in both: without -ffp-contract, results are the same
// bits, except hsum's order of additions and vfma (fused where the target has FMA).
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
inline float hsum(vf v) { return _mm512_reduce_add_ps((__m512)v); }
inline vf vfma(vf a, vf b, vf c) { return (vf)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c); }
inline vf vsqrt(vf x) { return (vf)_mm512_sqrt_ps((__m512)x); }

#else

typedef float f8 __attribute__((vector_size(32)));
typedef int32_t i8 __attribute__((vector_size(32)));

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
static_assert(sizeof(vf) == 64 && sizeof(vi) == 64, "16 lanes, no padding");

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
inline vi operator~(vi a) { return vi{~a.lo, ~a.hi}; }
inline vi operator<<(vi a, int n) { return vi{a.lo << n, a.hi << n}; }

const vi LANE = {i8{0, 1, 2, 3, 4, 5, 6, 7}, i8{8, 9, 10, 11, 12, 13, 14, 15}};

inline vf vf1(float x) {
  const f8 h = {x, x, x, x, x, x, x, x};
  return vf{h, h};
}
inline vi as_vi(vf x) { return vi{(i8)x.lo, (i8)x.hi}; }
inline vf as_vf(vi x) { return vf{(f8)x.lo, (f8)x.hi}; }
inline vi to_vi(vf x) { return vi{__builtin_convertvector(x.lo, i8), __builtin_convertvector(x.hi, i8)}; }
inline vf to_vf(vi x) { return vf{__builtin_convertvector(x.lo, f8), __builtin_convertvector(x.hi, f8)}; }

#if defined(__AVX__)
inline bool any(vi m) { return _mm256_movemask_ps((__m256)(m.lo | m.hi)) != 0; }
inline bool all(vi m) { return _mm256_movemask_ps((__m256)(m.lo & m.hi)) == 0xFF; }
inline float hsum(vf v) {
  const __m256 s8 = (__m256)(v.lo + v.hi);
  const __m128 s4 = _mm_add_ps(_mm256_castps256_ps128(s8), _mm256_extractf128_ps(s8, 1));
  const __m128 s2 = _mm_add_ps(s4, _mm_movehl_ps(s4, s4));
  return _mm_cvtss_f32(_mm_add_ss(s2, _mm_movehdup_ps(s2)));
}
inline vf vsqrt(vf x) { return vf{(f8)_mm256_sqrt_ps((__m256)x.lo), (f8)_mm256_sqrt_ps((__m256)x.hi)}; }
#else
inline bool any(vi m) {
  for (int i = 0; i < 16; ++i)
    if (m[i]) return true;
  return false;
}
inline bool all(vi m) {
  for (int i = 0; i < 16; ++i)
    if (!m[i]) return false;
  return true;
}
inline float hsum(vf v) {
  const f8 s8 = v.lo + v.hi;
  return ((s8[0] + s8[4]) + (s8[1] + s8[5])) + ((s8[2] + s8[6]) + (s8[3] + s8[7]));
}
inline vf vsqrt(vf x) {
  for (int i = 0; i < 16; ++i) x[i] = std::sqrt(x[i]);
  return x;
}
#endif

#if defined(__FMA__)
inline vf vfma(vf a, vf b, vf c) {
  return vf{(f8)_mm256_fmadd_ps((__m256)a.lo, (__m256)b.lo, (__m256)c.lo),
            (f8)_mm256_fmadd_ps((__m256)a.hi, (__m256)b.hi, (__m256)c.hi)};
}
#else
inline vf vfma(vf a, vf b, vf c) { return a * b + c; }
#endif

#endif  // AVX-512

inline vi vi1(int32_t x) { return vi{} + x; }
inline vf select(vi m, vf a, vf b) { return as_vf((as_vi(a) & m) | (as_vi(b) & ~m)); }
inline vi select(vi m, vi a, vi b) { return (a & m) | (b & ~m); }
inline vf vfma(vf a, float b, vf c) { return vfma(a, vf1(b), c); }

}  // namespace
