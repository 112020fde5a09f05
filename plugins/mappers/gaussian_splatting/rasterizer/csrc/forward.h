// The CPU rasteriser's forward pass (cpu_rasterizer.cpp, "Forward" in its first comment).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include "slk_thread_pool.h"  // (slamkit/csrc) Pool, parallel_for
#include "composite.h"
#include "render_state.h"

namespace {

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
  S.entry_blocks.resize(num_entries);
  S.entry_alphas.resize(num_entries);
  if (S.alpha_budget) S.entry_xl.resize(num_entries);
  S.last.resize((size_t)W * H);
  std::vector<int64_t> pairs_per_thread(std::max(nthreads, 1), 0), lanes_per_thread(std::max(nthreads, 1), 0),
      stored_per_thread(std::max(nthreads, 1), 0),
      tiles_per_thread(std::max(nthreads, 1), 0);
  parallel_for(nthreads, tiles, 1, [&](int64_t b, int64_t e, int tid) {
    std::unique_ptr<ChunkVisits> chunk(new ChunkVisits);
    ChunkVisits& C = *chunk;
    for (int64_t ti = b; ti < e; ++ti) {
      const int tile = S.tile_order[ti];
      const int tx = tile % S.tiles_x, ty = tile / S.tiles_x;
      const int x0 = tx * TILE, y0 = ty * TILE;
      const int tw = std::min(TILE, W - x0), th = std::min(TILE, H - y0);
      TileState st(tw, th);
      int64_t lanes = 0, stored_lanes = 0;
      AlphaStore& store = S.alpha_store[tid];
      S.tile_store[tile] = tid;
      S.tile_block[tile] = (int64_t)store.size;
      int32_t tile_blocks = 0;
      const int end = S.tile_start[tile + 1];
      for (int cs = S.tile_start[tile]; cs < end && st.alive; cs += CHUNK) {
        const int ce = std::min(end, cs + CHUNK);
        C.list(S, cs, ce, end, x0, y0, tw, th, st.alive);
        C.compute_alphas(x0);
        lanes += (int64_t)C.visits * BLOCK;
        // kept for the backward where they fit (AlphaStore; else the backward recomputes them),
        // with the entries' span starts
        const size_t stored = S.tile_block[tile] + tile_blocks + C.visits;
        const bool keep = C.visits > 0 && stored <= S.alpha_budget;
        if (keep) {
          store.reserve(stored, S.alpha_budget);
          vblock* kept = store.data.get() + S.tile_block[tile] + tile_blocks;
          for (int v = 0; v < C.visits; ++v) store_streaming(kept + v, C.alphas[v]);
          for (int k = 0; k < ce - cs; ++k) S.entry_xl[cs + k] = *(const vi*)C.ents[k].sp.xl;
          stored_lanes += (int64_t)C.visits * BLOCK;
        }
        for (int k = 0; k < ce - cs; ++k) S.entry_alphas[cs + k] = keep ? tile_blocks + C.first_visit[k] : -1;
        tile_blocks += keep ? C.visits : 0;
        for (uint32_t m = C.listed; m; m &= m - 1) st.composite(__builtin_ctz(m), C);
      }
      store.size = S.tile_block[tile] + tile_blocks;
      st.write(S, x0, y0, tw, th, bg, out_color, out_depth, out_alpha);
      pairs_per_thread[tid] += st.pairs();
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

}  // namespace
