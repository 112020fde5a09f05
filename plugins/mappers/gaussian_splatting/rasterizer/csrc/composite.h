// The CPU rasteriser's compositing of one tile (forward.h, step 5): a chunk of the tile's list as
// visits (an entry on a block of a tile row it covers) with their alphas, and the tile's state
// that composites the chunk block by block.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>

#include "render_state.h"

namespace {

// A chunk of a tile's list (up to CHUNK entries from position cs): their row spans and paint, the
// blocks each covers as visits, numbered entry by entry (each entry's blocks in bit order; visit
// v is entry[v] / BLOCKS on block entry[v] % BLOCKS), each block's visits in depth order, and the
// visits' alphas.
struct ChunkVisits {
  static constexpr int MAX = CHUNK * BLOCKS + GROUP;  // (GROUP: the padding of the last group)
  static_assert(CHUNK * BLOCKS <= 65536, "a chunk's visits are numbered in uint16_t");
  ChunkEntry ents[CHUNK];
  EntryPaint paint[CHUNK];
  int first_visit[CHUNK + 1];  // entry k's visits are [first_visit[k], first_visit[k + 1])
  uint16_t entry[MAX];
  alignas(64) vblock alphas[MAX];
  int count[BLOCKS];  // per block: its visits, block_visits[bit][0, count)
  uint16_t block_visits[BLOCKS][CHUNK];
  uint32_t listed = 0;  // blocks with visits
  int visits = 0;

  // Lists the entries at [cs, ce) of the tile at (x0, y0), tw x th pixels, whose list ends at
  // `end`, on the blocks in `alive`; records each entry's blocks in S.entry_blocks.
  void list(State& S, int cs, int ce, int end, int x0, int y0, int tw, int th, uint32_t alive) {
    std::fill(count, count + BLOCKS, 0);
    listed = 0;
    visits = 0;
    for (int pos = cs; pos < ce; ++pos) {
      if (pos + PREFETCH < end) __builtin_prefetch(&S.splats[S.tile_ids[pos + PREFETCH]]);
      const Splat& s = S.splats[S.tile_ids[pos]];
      const int k = pos - cs;
      ChunkEntry& E = ents[k];
      row_spans(s, y0, S.W, E.sp);
      E.a = s.a;
      paint[k] = EntryPaint{{s.col[0], s.col[1], s.col[2]}, s.z, pos};
      const uint32_t met = alive & blocks_met(E.sp, std::max(s.y0 - y0, 0), std::min(s.y1 - y0, th - 1), x0, tw);
      first_visit[k] = visits;
      for (uint32_t m = met; m; m &= m - 1, ++visits) {
        const int bit = __builtin_ctz(m);
        block_visits[bit][count[bit]++] = (uint16_t)visits;
        entry[visits] = (uint16_t)(k * BLOCKS + bit);
      }
      listed |= met;
      S.entry_blocks[pos] = met;
    }
    first_visit[ce - cs] = visits;
  }

  // The visits' alphas (visit_alphas).
  void compute_alphas(int x0) { visit_alphas(ents, entry, visits, x0, alphas); }
};

// A tile's compositing state, per block: transmittance, colour, depth and alpha sums, last
// contributing list position, done lanes; the blocks with lanes not done, and the pairs composited.
struct TileState {
  vblock T[BLOCKS], c0[BLOCKS], c1[BLOCKS], c2[BLOCKS], dep[BLOCKS], acc[BLOCKS];
  iblock last[BLOCKS], done[BLOCKS];
  uint32_t alive = 0;
  iblock pairs_per_lane{};  // composited

  TileState(int tw, int th) {
    for (int bit = 0; bit < BLOCKS; ++bit) {
      T[bit] = block_of(1.0f);
      c0[bit] = c1[bit] = c2[bit] = dep[bit] = acc[bit] = vblock{};
      last[bit] = iblock{} - 1;
      done[bit] = block_row(bit) < th ? block_lanes() + block_lane0(bit) >= tw : iblock{} - 1;
      alive |= (uint32_t)!all(done[bit]) << bit;
    }
  }

  // Composites block `bit` through its visits in the chunk, with its state in registers; a block
  // whose lanes are all done leaves `alive`.
  void composite(int bit, const ChunkVisits& C) {
    vblock rT = T[bit], r0c = c0[bit], r1c = c1[bit], r2c = c2[bit], rdep = dep[bit], racc = acc[bit];
    iblock rlast = last[bit], rdone = done[bit], rpairs = pairs_per_lane;
    for (int j = 0; j < C.count[bit]; ++j) {
      const int v = C.block_visits[bit][j];
      const EntryPaint& P = C.paint[C.entry[v] / BLOCKS];
      const vblock al = C.alphas[v];
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
      rpairs -= covered;
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
    pairs_per_lane = rpairs;
  }

  // The tile's pixels (first column x0, row y0, tw x th) into the outputs (W wide), with the
  // background bg behind them; each pixel's final transmittance and last position into S.
  void write(State& S, int x0, int y0, int tw, int th, const float* bg, float* out_color, float* out_depth,
             float* out_alpha) const {
    // (the blocks' lanes, in memory, are the tile's pixels row by row)
    const float *Tp = pixels(T), *c0p = pixels(c0), *c1p = pixels(c1), *c2p = pixels(c2);
    for (int lr = 0; lr < th; ++lr) {
      const size_t q0 = (size_t)(y0 + lr) * S.W + x0;
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
  }

  int64_t pairs() const {
    int64_t n = 0;
    for (int i = 0; i < BLOCK; ++i) n += pairs_per_lane[i];
    return n;
  }
};

}  // namespace
