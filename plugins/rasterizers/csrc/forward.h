// The CPU rasteriser's forward pass (cpu_rasterizer.cpp, "Forward" in its first comment).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include "slk_thread_pool.h"  // (slamkit/csrc) Pool, parallel_for
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
  S.entry_block.resize(num_entries);
  S.entry_rows.resize(num_entries);
  S.entry_xl.resize(num_entries);
  S.last.resize((size_t)W * H);
  std::vector<int64_t> pairs_per_thread(std::max(nthreads, 1), 0), lanes_per_thread(std::max(nthreads, 1), 0),
      stored_per_thread(std::max(nthreads, 1), 0),
      tiles_per_thread(std::max(nthreads, 1), 0);
  parallel_for(nthreads, tiles, 1, [&](int64_t b, int64_t e, int tid) {
    std::unique_ptr<ChunkEntry[]> ents(new ChunkEntry[CHUNK]);
    // a chunk's visits (an entry on a block it covers, entry by entry, each entry's blocks in bit
    // order: k * BLOCKS + bit for entry k) and their alphas (the store keeps a copy where it can)
    constexpr int MAX_VISITS = CHUNK * BLOCKS + GROUP;
    static_assert(CHUNK * BLOCKS <= 65536, "a chunk's visits are numbered in uint16_t");
    std::unique_ptr<uint16_t[]> visit_(new uint16_t[MAX_VISITS]);
    std::unique_ptr<vblock[]> alphas_(new vblock[MAX_VISITS]);
    uint16_t* const visit = visit_.get();
    vblock* const alphas = alphas_.get();
    for (int64_t ti = b; ti < e; ++ti) {
      const int tile = S.tile_order[ti];
      const int tx = tile % S.tiles_x, ty = tile / S.tiles_x;
      const int x0 = tx * TILE, y0 = ty * TILE;
      const int tw = std::min(TILE, W - x0), th = std::min(TILE, H - y0);
      // per block: transmittance, colour, depth and alpha sums, last position, done lanes
      vblock T[BLOCKS], c0[BLOCKS], c1[BLOCKS], c2[BLOCKS], dep[BLOCKS], acc[BLOCKS];
      iblock last[BLOCKS], done[BLOCKS];
      uint32_t alive = 0;  // blocks with lanes not done
      for (int bit = 0; bit < BLOCKS; ++bit) {
        const int lr = bit / HALVES, lane0 = bit % HALVES * BLOCK;
        T[bit] = block_of(1.0f);
        c0[bit] = c1[bit] = c2[bit] = dep[bit] = acc[bit] = vblock{};
        last[bit] = iblock{} - 1;
        done[bit] = lr < th ? block_lanes() + lane0 >= tw : iblock{} - 1;
        alive |= (uint32_t)!all(done[bit]) << bit;
      }
      int64_t lanes = 0, stored_lanes = 0;
      iblock count = iblock{};
      AlphaStore& store = S.alpha_store[tid];
      S.tile_store[tile] = tid;
      S.tile_block[tile] = (int64_t)store.size;
      int32_t tile_blocks = 0;
      const int end = S.tile_start[tile + 1];
      for (int cs = S.tile_start[tile]; cs < end && alive; cs += CHUNK) {
        // the chunk's entries: their row spans and the blocks they cover (blocks already done
        // are skipped), as visits, and per block its visits in depth order
        const int ce = std::min(end, cs + CHUNK);
        int nrow[BLOCKS] = {};
        uint16_t list[BLOCKS][CHUNK];
        EntryPaint paint[CHUNK];
        int first_visit[CHUNK];
        uint32_t listed = 0;  // blocks with entries
        int visits = 0;
        for (int pos = cs; pos < ce; ++pos) {
          if (pos + PREFETCH < end) __builtin_prefetch(&S.splats[S.tile_ids[pos + PREFETCH]]);
          const Splat& s = S.splats[S.tile_ids[pos]];
          const int k = pos - cs;
          ChunkEntry& E = ents[k];
          row_spans(s, y0, W, E.sp);
          E.a = s.a;
          paint[k] = EntryPaint{{s.col[0], s.col[1], s.col[2]}, s.z, pos};
          const uint32_t met = alive & blocks_met(E.sp, std::max(s.y0 - y0, 0), std::min(s.y1 - y0, th - 1), x0, tw);
          first_visit[k] = visits;
          for (uint32_t m = met; m; m &= m - 1, ++visits) {
            const int bit = __builtin_ctz(m);
            list[bit][nrow[bit]++] = (uint16_t)visits;
            visit[visits] = (uint16_t)(k * BLOCKS + bit);
          }
          listed |= met;
          S.entry_rows[pos] = met;
          S.entry_xl[pos] = *(const vi*)E.sp.xl;
        }
        // the visits' alphas, GROUP at a time (the last group padded with its last visit)
        for (int v = visits; v % GROUP; ++v) visit[v] = visit[visits - 1];
        for (int v = 0; v < visits; v += GROUP) {
          const ChunkEntry* E[GROUP];
          int lr[GROUP], lane0[GROUP];
          for (int g = 0; g < GROUP; ++g) {
            const int bit = visit[v + g] % BLOCKS;
            E[g] = &ents[visit[v + g] / BLOCKS];
            lr[g] = bit / HALVES;
            lane0[g] = bit % HALVES * BLOCK;
          }
          block_alphas<GROUP>(E, lr, lane0, x0, alphas + v);
        }
        lanes += (int64_t)visits * BLOCK;
        // kept for the backward where they fit (AlphaStore; else the backward recomputes them)
        const size_t stored = S.tile_block[tile] + tile_blocks + visits;
        const bool keep = stored <= S.alpha_budget;
        if (keep) {
          store.reserve(stored, S.alpha_budget);
          vblock* kept = store.data.get() + S.tile_block[tile] + tile_blocks;
          for (int v = 0; v < visits; ++v) store_streaming(kept + v, alphas[v]);
          stored_lanes += (int64_t)visits * BLOCK;
        }
        for (int pos = cs; pos < ce; ++pos) S.entry_block[pos] = keep ? tile_blocks + first_visit[pos - cs] : -1;
        tile_blocks += keep ? visits : 0;
        // composite block by block, the block's state in registers
        for (uint32_t m = listed; m; m &= m - 1) {
          const int bit = __builtin_ctz(m);
          vblock rT = T[bit], r0c = c0[bit], r1c = c1[bit], r2c = c2[bit], rdep = dep[bit], racc = acc[bit];
          iblock rlast = last[bit], rdone = done[bit];
          for (int j = 0; j < nrow[bit]; ++j) {
            const int v = list[bit][j];
            const EntryPaint& P = paint[visit[v] / BLOCKS];
            const vblock al = alphas[v];
            // lanes outside the span have alpha 0: they change nothing but stay undone
            const vblock Tn = rT * (1.0f - al);
            const iblock now_done = rdone | (Tn < (float)T_MIN);
            const vblock w = select(now_done, vblock{}, al * rT);
            r0c = vfma(w, block_of(P.col[0]), r0c);
            r1c = vfma(w, block_of(P.col[1]), r1c);
            r2c = vfma(w, block_of(P.col[2]), r2c);
            rdep = vfma(w, block_of(P.z), rdep);
            racc += w;
            rT = select(now_done, rT, Tn);
            const iblock covered = ~now_done & (al > 0.0f);
            rlast = select(covered, iblock{} + P.pos, rlast);
            count -= covered;
            rdone = now_done;  // (branch-free: stops are too frequent and irregular to predict)
            if (all(rdone)) {
              alive &= ~(1u << bit);
              break;
            }
          }
          T[bit] = rT;
          c0[bit] = r0c;
          c1[bit] = r1c;
          c2[bit] = r2c;
          dep[bit] = rdep;
          acc[bit] = racc;
          last[bit] = rlast;
          done[bit] = rdone;
        }
      }
      store.size = S.tile_block[tile] + tile_blocks;
      // (the blocks' lanes, in memory, are the tile's pixels row by row)
      const float *Tp = pixels(T), *c0p = pixels(c0), *c1p = pixels(c1), *c2p = pixels(c2);
      for (int lr = 0; lr < th; ++lr) {
        const size_t q0 = (size_t)(y0 + lr) * W + x0;
        const int i0 = lr * TILE;
        for (int lc = 0; lc < tw; ++lc) {
          // the background shows through T = 1 - sum w (T is the more accurate where alpha ~ 1)
          const float rest = Tp[i0 + lc];
          out_color[3 * (q0 + lc)] = c0p[i0 + lc] + rest * bg[0];
          out_color[3 * (q0 + lc) + 1] = c1p[i0 + lc] + rest * bg[1];
          out_color[3 * (q0 + lc) + 2] = c2p[i0 + lc] + rest * bg[2];
        }
        std::memcpy(out_depth + q0, pixels(dep) + i0, tw * sizeof(float));
        std::memcpy(out_alpha + q0, pixels(acc) + i0, tw * sizeof(float));
        std::memcpy(&S.T_final[q0], Tp + i0, tw * sizeof(float));
        std::memcpy(&S.last[q0], pixels(last) + i0, tw * sizeof(int32_t));
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

}  // namespace
