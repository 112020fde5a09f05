// What a CPU rasteriser render keeps between its forward and backward passes (cpu_rasterizer.cpp),
// and the helpers both passes share: phase timing, the depth sort.
#pragma once

#include <chrono>
#include <cstdint>
#include <cstring>
#include <ctime>
#include <vector>

#include "alpha_store.h"
#include "conventions.h"
#include "projection.h"
#include "splats.h"

namespace {

struct Stamp {  // wall-clock and process CPU time, microseconds
  int64_t wall, cpu;
};

inline Stamp now_us() {
  Stamp s;
  s.wall = std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::steady_clock::now().time_since_epoch())
               .count();
  s.cpu = (int64_t)((double)std::clock() * 1e6 / CLOCKS_PER_SEC);
  return s;
}

struct State {
  int N = 0, M = 0, W = 0, H = 0, tiles_x = 0, tiles_y = 0;
  Camera cam;
  std::vector<Splat> splats;            // M, depth order
  std::vector<int32_t> tile_start;      // tiles + 1
  std::vector<int32_t> tile_ids;        // entries: splat index, depth order within a tile
  std::vector<int32_t> tile_slot;       // entries: slot of the entry (Gaussian-major order)
  std::vector<int32_t> sorted_of;       // N: depth rank of input Gaussian i, -1 if culled
  std::vector<int32_t> slot_start;      // M + 1: slots of splat i are [slot_start[i], slot_start[i+1])
  std::vector<int32_t> tile_order;      // tiles by decreasing list length (load balance)
  std::vector<float> T_final;           // H*W
  std::vector<int32_t> last;            // H*W: last composited position in the tile list, -1 none
  size_t alpha_budget = 0;              // blocks each forward thread may store (AlphaStore)
  std::vector<AlphaStore> alpha_store;  // per forward thread
  std::vector<int32_t> tile_store;      // tiles: the thread whose store holds the tile's alphas
  std::vector<int64_t> tile_block;      // tiles: the tile's first block in that store
  // per entry of the chunks composited (the backward reads no others):
  std::vector<uint32_t> entry_blocks;   // the blocks it was composited on (bit lr * HALVES + h)
  std::vector<int32_t> entry_alphas;    // where its alphas are in the tile's stored ones (-1: not stored)
  std::vector<vi> entry_xl;             // where they are stored: its span starts (RowSpans::xl)
  int64_t num_pairs = 0;
  int64_t num_rows = 0;  // vector steps of the forward pass, in 16-lane units (an 8-lane half counts 1/2)
  int64_t num_rows_stored = 0;  // of those, the ones whose alphas were kept for the backward
  int threads_used = 0;  // threads that composited at least one tile in the forward pass
  // per phase (forward: project, sort, bin, lists, composite; backward: tiles, reduce): wall, CPU
  int64_t wall_us[8] = {0}, cpu_us[8] = {0};

  ~State() { AlphaStorePool::instance().give(alpha_store, alpha_budget * alpha_store.size()); }
};

void radix_sort_by_key(std::vector<uint32_t>& key, std::vector<int32_t>& val) {
  size_t n = key.size();
  std::vector<uint32_t> k2(n);
  std::vector<int32_t> v2(n);
  for (int shift = 0; shift < 32; shift += 11) {
    size_t count[2049] = {0};
    for (size_t i = 0; i < n; ++i) ++count[((key[i] >> shift) & 2047) + 1];
    for (int d = 0; d < 2048; ++d) count[d + 1] += count[d];
    for (size_t i = 0; i < n; ++i) {
      size_t j = count[(key[i] >> shift) & 2047]++;
      k2[j] = key[i];
      v2[j] = val[i];
    }
    key.swap(k2);
    val.swap(v2);
  }
}

inline uint32_t float_bits(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  return u;
}

}  // namespace
