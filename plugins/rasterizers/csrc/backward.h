// The CPU rasteriser's backward pass (cpu_rasterizer.cpp, "Backward" in its first comment).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <type_traits>
#include <vector>

#include "slk_thread_pool.h"  // (slamkit/csrc) Pool, parallel_for
#include "render_state.h"

namespace {

constexpr int NUM_MOMENTS = 10;  // accumulated per (tile, Gaussian) entry (backward, step 1)

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

}  // namespace
