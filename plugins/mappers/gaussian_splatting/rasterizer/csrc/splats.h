// A projected Gaussian as the CPU rasteriser's tiles see it (cpu_rasterizer.cpp): its splat (one
// cache line), its covered columns on 16 rows at once, and its alphas on a block of a tile row.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "slk_vec16.h"  // (slamkit/csrc) 16-lane vectors
#include "conventions.h"

namespace {

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

// exp of G blocks of float lanes (Cephes' expf: range reduction by ln 2, degree-6 polynomial;
// within ~1 ulp of the correctly rounded value on [-87, 0], which is all that alpha needs). The
// G are computed stage by stage: their dependency chains (~60 cycles each) interleave, where the
// out-of-order window of one loop over blocks holds barely more than one exp. The polynomial by
// Estrin's scheme (three levels deep, not Horner's six): a shorter chain still.
template <int G>
inline void vexp(vblock* x) {
  vblock n[G], r[G];
  iblock e[G];
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) {
    x[k] = select(x[k] < -87.0f, block_of(-87.0f), x[k]);
    const vblock t = x[k] * 1.44269504088896341f + 12582912.0f;  // 1.5 * 2^23: rounds x log2(e) to an integer
    n[k] = t - 12582912.0f;
    e[k] = (as_vi(t) - 0x4B400000 + 127) << 23;  // the bits of 2^n
  }
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) r[k] = vfma(n[k], block_of(2.12194440e-4f), vfma(n[k], block_of(-0.693359375f), x[k]));
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) {
    const vblock r2 = r[k] * r[k];
    const vblock hi = vfma(block_of(1.9875691500E-4f), r[k], block_of(1.3981999507E-3f));
    const vblock mid = vfma(block_of(8.3334519073E-3f), r[k], block_of(4.1665795894E-2f));
    const vblock lo = vfma(block_of(1.6666665459E-1f), r[k], block_of(5.0000001201E-1f));
    const vblock p = vfma(vfma(hi, r2, mid), r2, lo);
    x[k] = (vfma(p, r2, r[k]) + 1.0f) * as_vf(e[k]);
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

// The part of the row spans (RowSpans) that the backward needs where the forward's alphas were
// stored, from the span starts xl the forward kept: xl, row_dx and dy, as row_spans computes them
// (no square root or division).
inline void spans_from_starts(const Splat& s, const vi& xl, int y0, RowSpans& o) {
  *(vi*)o.xl = xl;
  *(vf*)o.dy = to_vf(LANE + y0) - s.v;
  *(vf*)o.row_dx = to_vf(xl) - s.u;
}

// Compositing a tile goes chunk by chunk (CHUNK entries): the entries' row spans are computed
// (16 rows at once) and the blocks each covers listed, then the alphas of every listed (block,
// entry) pair are computed, then each block is composited through its entries with its state in
// registers.
constexpr int CHUNK = 64;
constexpr int PREFETCH = 8;  // entries ahead whose splat is prefetched (they are scattered in memory)
struct ChunkEntry {
  RowSpans sp;
  float a;
};
struct EntryPaint {  // what compositing adds of an entry: colour, depth, its tile list position
  float col[3], z;
  int32_t pos;
};

// The lanes of a tile row are processed a block at a time (slk_vec16.h: the whole row with
// AVX-512, else each 8-lane half that the entry's span meets; a span covers ~5-7 of the 16
// pixels on average, so most need one half). Block lr * HALVES + h is half h of row lr; a tile's
// blocks fit the bits of a uint32_t.
constexpr int BLOCK = TILE / HALVES;
constexpr int BLOCKS = TILE * HALVES;
static_assert(BLOCKS <= 32, "a tile's blocks are the bits of a uint32_t");
inline int block_row(int bit) { return bit / HALVES; }
inline int block_lane0(int bit) { return bit % HALVES * BLOCK; }  // its first lane in the tile row

// the lanes of a tile's blocks (each block's lanes in turn: the tile's pixels row by row)
inline const float* pixels(const vblock* v) { return reinterpret_cast<const float*>(v); }
inline const int32_t* pixels(const iblock* v) { return reinterpret_cast<const int32_t*>(v); }
inline float* pixels(vblock* v) { return reinterpret_cast<float*>(v); }
inline int32_t* pixels(iblock* v) { return reinterpret_cast<int32_t*>(v); }

// bit i of a 16-bit row mask moved to bit i * HALVES + h
inline uint32_t spread_rows(uint32_t rows, int h) {
  if (HALVES == 1) return rows;
  rows = (rows | rows << 8) & 0x00FF00FFu;  // (the bit interleave; pdep is microcoded on AMD before Zen 3)
  rows = (rows | rows << 4) & 0x0F0F0F0Fu;
  rows = (rows | rows << 2) & 0x33333333u;
  rows = (rows | rows << 1) & 0x55555555u;
  return rows << h;
}

// The blocks of the tile (first column x0, tw columns wide) that an entry's spans on rows
// [r0, r1] meet, as bits (above).
inline uint32_t blocks_met(const RowSpans& sp, int r0, int r1, int x0, int tw) {
  const vi a = *(const vi*)sp.xl - x0, z = *(const vi*)sp.xr - x0;  // the spans in tile columns
  const vi rows = (LANE >= r0) & (LANE <= r1) & (z >= a);
  uint32_t met = 0;
  for (int h = 0; h < HALVES; ++h)
    met |= spread_rows(lane_bits(rows & (a < std::min(tw, (h + 1) * BLOCK)) & (z >= h * BLOCK)), h);
  return met;
}

// dx of the block of row lr whose first lane is lane0: lane - span start a + row_dx (a = xl - x0)
inline vblock block_dx(const RowSpans& sp, int lr, int a, int lane0) {
  return to_vf(block_lanes() + (lane0 - a)) + sp.row_dx[lr];
}

// Entries' alphas on blocks, G at a time (so that their exps interleave, vexp): entry E[k] on the
// block of row lr[k] whose first lane is lane0[k] (tile columns; the tile's first column is x0),
// 0 outside its span on that row. log alpha is the torch backend's expression (fused here: it
// does not decide which pixels are covered). Both passes read "alpha > 0" as "covered": inside a
// span alpha is at least exp(-87) (vexp's clamp; a normal float), and the clamp to ALPHA_MAX
// below sends a NaN to ALPHA_MAX (keep its argument order).
template <int G>
inline void block_alphas(const ChunkEntry* const* E, const int* lr, const int* lane0, int x0, vblock* al) {
  iblock in[G];
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) {
    const RowSpans& sp = E[k]->sp;
    const int a = sp.xl[lr[k]] - x0, z = sp.xr[lr[k]] - x0;
    const vblock dx = block_dx(sp, lr[k], a, lane0[k]);
    al[k] = vfma(dx * -0.5f, vfma(dx, block_of(E[k]->a), block_of(sp.row_b[lr[k]])), block_of(sp.row_k[lr[k]]));
    const iblock lane = block_lanes() + lane0[k];
    in[k] = (lane >= a) & (lane <= z);
  }
  vexp<G>(al);
#pragma GCC unroll 8
  for (int k = 0; k < G; ++k) al[k] = select(in[k], select(al[k] < ALPHA_MAX, al[k], block_of(ALPHA_MAX)), vblock{});
}

// entries whose alphas the forward computes at once (block_alphas)
constexpr int GROUP = 4;

// The alphas of n visits, visit v being entry ents[visit[v] / BLOCKS] on block visit[v] % BLOCKS,
// into out, GROUP at a time; visit[] and out hold n rounded up to GROUP (the last group is
// padded with its last visit).
inline void visit_alphas(const ChunkEntry* ents, uint16_t* visit, int n, int x0, vblock* out) {
  for (int v = n; v % GROUP; ++v) visit[v] = visit[n - 1];
  for (int v = 0; v < n; v += GROUP) {
    const ChunkEntry* E[GROUP];
    int lr[GROUP], lane0[GROUP];
    for (int g = 0; g < GROUP; ++g) {
      E[g] = &ents[visit[v + g] / BLOCKS];
      lr[g] = block_row(visit[v + g] % BLOCKS);
      lane0[g] = block_lane0(visit[v + g] % BLOCKS);
    }
    block_alphas<GROUP>(E, lr, lane0, x0, out + v);
  }
}

}  // namespace
