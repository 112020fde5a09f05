// The CPU rasteriser's backward pass (cpu_rasterizer.cpp, "Backward" in its first comment).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include "slk_thread_pool.h"  // (slamkit/csrc) Pool, parallel_for
#include "render_state.h"

namespace {

constexpr int NUM_MOMENTS = 10;  // accumulated per (tile, Gaussian) entry (backward, step 1)

// A tile's alphas as the forward pass stored them (AlphaStore): entry by entry, each entry's
// blocks in bit order.
class StoredAlphas {
 public:
  StoredAlphas(const State& S, int tile) : S_(S), start_(S.tile_start[tile]), end_(S.tile_start[tile + 1]) {
    const AlphaStore& store = S.alpha_store[S.tile_store[tile]];
    tile_ = store.data ? store.data.get() + S.tile_block[tile] : nullptr;
  }

  // The alphas of the entry at pos on its blocks, or nullptr where its chunk was not stored (the
  // backward recomputes them). The first entry asked for in a chunk reads the whole chunk's
  // blocks in (stream_in).
  const vblock* entry(int pos) {
    if (S_.entry_alphas[pos] < 0) return nullptr;
    const int cs = start_ + (pos - start_) / CHUNK * CHUNK;
    if (cs != chunk_) {
      chunk_ = cs;
      const int last = std::min(end_, cs + CHUNK) - 1;
      stream_in(tile_ + S_.entry_alphas[cs], tile_ + S_.entry_alphas[last] + __builtin_popcount(S_.entry_blocks[last]));
    }
    return tile_ + S_.entry_alphas[pos];
  }

 private:
  const State& S_;
  const vblock* tile_;  // the tile's first block
  int start_, end_, chunk_ = -1;
};

// The alphas of entry E on its blocks (bit order) as the forward computed them, into out
// (BLOCKS + GROUP blocks).
inline void recompute_alphas(const ChunkEntry& E, uint32_t blocks, int x0, vblock* out) {
  uint16_t visit[BLOCKS + GROUP];
  int n = 0;
  for (; blocks; blocks &= blocks - 1) visit[n++] = (uint16_t)__builtin_ctz(blocks);  // (entry 0: E)
  visit_alphas(&E, visit, n, x0, out);
}

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
      // per block: transmittance (after the current entry), suffix sum of w v, output grads
      vblock T[BLOCKS], Ssum[BLOCKS], g0[BLOCKS], g1[BLOCKS], g2[BLOCKS], gd[BLOCKS], ga[BLOCKS];
      iblock last[BLOCKS];
      int maxlast = -1;
      for (int bit = 0; bit < BLOCKS; ++bit) {
        T[bit] = Ssum[bit] = g0[bit] = g1[bit] = g2[bit] = gd[bit] = ga[bit] = vblock{};
        last[bit] = iblock{} - 1;
      }
      double b0 = 0, b1 = 0, b2 = 0;  // d colour / d bg = T
      // (the blocks' lanes, in memory, are the tile's pixels row by row)
      float *Tp = pixels(T), *g0p = pixels(g0), *g1p = pixels(g1), *g2p = pixels(g2);
      float *gdp = pixels(gd), *gap = pixels(ga);
      int32_t* lastp = pixels(last);
      for (int lr = 0; lr < th; ++lr) {
        const size_t q0 = (size_t)(y0 + lr) * W + x0;
        const int i0 = lr * TILE;
        std::memcpy(Tp + i0, &S.T_final[q0], tw * sizeof(float));
        std::memcpy(gdp + i0, g_depth + q0, tw * sizeof(float));
        std::memcpy(lastp + i0, &S.last[q0], tw * sizeof(int32_t));
        for (int lc = 0; lc < tw; ++lc) {
          const size_t q = q0 + lc;
          const int i = i0 + lc;
          g0p[i] = g_color[3 * q];
          g1p[i] = g_color[3 * q + 1];
          g2p[i] = g_color[3 * q + 2];
          // d colour / d (sum w) = -bg, folded into the alpha gradient
          gap[i] = g_alpha[q] - (g_color[3 * q] * bg[0] + g_color[3 * q + 1] * bg[1] + g_color[3 * q + 2] * bg[2]);
          maxlast = std::max(maxlast, lastp[i]);
          b0 += (double)Tp[i] * g_color[3 * q];
          b1 += (double)Tp[i] * g_color[3 * q + 1];
          b2 += (double)Tp[i] * g_color[3 * q + 2];
        }
      }
      bg_tile[3 * tile] = b0;
      bg_tile[3 * tile + 1] = b1;
      bg_tile[3 * tile + 2] = b2;
      ChunkEntry E;
      const RowSpans& sp = E.sp;
      StoredAlphas alphas(S, tile);
      alignas(64) vblock recomputed[BLOCKS + GROUP];
      for (int pos = end - 1; pos >= start; --pos) {
        float* mom = &moments[(size_t)S.tile_slot[pos] * NUM_MOMENTS];
        if (pos > maxlast || S.entry_blocks[pos] == 0) {  // (no pixel it covers composited it)
          for (int k = 0; k < NUM_MOMENTS; ++k) mom[k] = 0.0f;
          continue;
        }
        if (pos - PREFETCH >= start) __builtin_prefetch(&S.splats[S.tile_ids[pos - PREFETCH]]);
        const Splat& s = S.splats[S.tile_ids[pos]];
        // the entry's moments, summed over its blocks (lane by lane, then across)
        vblock m0{}, mx{}, my{}, mxx{}, mxy{}, myy{}, w0{}, w1{}, w2{}, wd{};
        const iblock posv = iblock{} + pos;
        // the entry's alphas on the blocks the forward pass composited it on (bit order): as
        // stored, or recomputed as the forward computed them
        const vblock* al = alphas.entry(pos);
        if (al) {
          spans_from_starts(s, S.entry_xl[pos], y0, E.sp);
        } else {
          row_spans(s, y0, W, E.sp);
          E.a = s.a;
          recompute_alphas(E, S.entry_blocks[pos], x0, recomputed);
          al = recomputed;
        }
        for (uint32_t blocks = S.entry_blocks[pos]; blocks; blocks &= blocks - 1, ++al) {
          const int bit = __builtin_ctz(blocks), lr = block_row(bit), lane0 = block_lane0(bit);
          // alpha > 0 exactly where the entry covers the pixel (block_alphas)
          const iblock m = (*al > 0.0f) & (posv <= last[bit]);
          if (!any(m)) continue;
          const vblock a = *al;
          const vblock dx = block_dx(sp, lr, sp.xl[lr] - x0, lane0);
          const vblock dy = block_of(sp.dy[lr]);
          const vblock inv = 1.0f / (1.0f - a);
          const vblock G0 = g0[bit], G1 = g1[bit], G2 = g2[bit], GD = gd[bit], GA = ga[bit], Sr = Ssum[bit];
          const vblock Tb = T[bit] * inv;  // transmittance before this Gaussian
          const vblock w = select(m, a * Tb, vblock{});
          const vblock val_c2 = vfma(block_of(s.col[2]), G2, vfma(block_of(s.z), GD, GA));
          const vblock val = vfma(block_of(s.col[0]), G0, vfma(block_of(s.col[1]), G1, val_c2));
          // dL/dlog(alpha) = alpha dL/dalpha = alpha (T v - sum_{j>i} w_j v_j / (1 - alpha)), zero
          // where alpha is clamped
          const vblock sg = select(m & (a < ALPHA_MAX), a * vfma(Tb, val, -(Sr * inv)), vblock{});
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
          Ssum[bit] = vfma(w, val, Sr);  // w = 0 outside m
          T[bit] = select(m, Tb, T[bit]);
        }
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

}  // namespace
