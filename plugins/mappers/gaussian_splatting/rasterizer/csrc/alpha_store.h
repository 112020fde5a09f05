// The CPU rasteriser's store of the forward pass's alphas, read back by its backward pass
// (cpu_rasterizer.cpp).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <vector>

#include <unistd.h>

#include "slk_vec16.h"  // (slamkit/csrc) 16-lane vectors

namespace {

// The forward's alphas, kept for the backward, which would otherwise recompute every pair's exp
// (the longest dependency chain of its loop; ~40 % of its time). Blocks are stored in the order
// the forward computes them (so it writes sequentially): per tile chunk by chunk, per chunk entry
// by entry, per entry its blocks in bit order (entry_blocks); entry_alphas says where an entry's
// start. Each compositing thread appends its tiles' blocks to its own store (grown by doubling up
// to its share of the budget, never initialised: the backward reads only blocks written); a
// chunk that would exceed it is not stored, and the backward recomputes its alphas.
struct AlphaStore {
  std::unique_ptr<vblock[]> data;
  size_t size = 0, cap = 0;  // in blocks
  void reserve(size_t n, size_t budget) {
    if (n <= cap) return;
    const size_t c = std::max(n, std::min(2 * cap, budget));
    std::unique_ptr<vblock[]> d(new vblock[c]);
    std::atomic_thread_fence(std::memory_order_seq_cst);  // (the streaming stores so far, before they are copied)
    if (cap) std::memcpy((void*)d.get(), (const void*)data.get(), cap * sizeof(vblock));  // the tile being written too
    data.swap(d);
    cap = c;
  }
};

// Reads the blocks [from, to) once, in address order, so that the hardware prefetcher streams
// them in: the backward then reads them in an order no prefetcher guesses (at 320x240, 3.7 ms
// of a 12.6 ms backward waited for them; software prefetches of the same lines did not help).
inline void stream_in(const vblock* from, const vblock* to) {
  float sink = 0.0f;
  for (const char* p = (const char*)from; p < (const char*)to; p += 64) sink += *(const float*)p;
  __asm__ __volatile__("" : : "g"(sink));  // (keeps the loads)
}

// A block written past the caches (non-temporal: the line is not read first; the backward reads
// it back much later); visible to other threads after fence_streaming().
inline void store_streaming(vblock* p, vblock v) {
#if defined(__AVX512F__)
  _mm512_stream_ps((float*)p, (__m512)v);
#elif defined(__AVX__)
  _mm256_stream_ps((float*)p, (__m256)v);
#else
  *p = v;
#endif
}
inline void fence_streaming() {
#if defined(__AVX512F__) || defined(__AVX__)
  _mm_sfence();
#endif
}

// Stores outlive the render that filled them and are handed to the next: a fresh store a render
// (~15 MB at 320x240) would cost a page fault every 4 KB, most of what keeping the alphas saves.
// The pool keeps about one render's worth (the budget of the render giving its stores back).
class AlphaStorePool {
 public:
  static AlphaStorePool& instance() {  // (as Pool::instance: never destroyed, one per process)
    static std::mutex m;
    static AlphaStorePool* pool = nullptr;
    static int64_t pid = -1;
    std::lock_guard<std::mutex> lock(m);
    const int64_t now = (int64_t)::getpid();
    if (pool == nullptr || pid != now) {  // a forked child must not wait on the parent's lock
      pool = new AlphaStorePool();
      pid = now;
    }
    return *pool;
  }
  AlphaStore take() {
    std::lock_guard<std::mutex> lock(mu_);
    if (free_.empty()) return AlphaStore();
    AlphaStore st = std::move(free_.back());
    free_.pop_back();
    kept_ -= st.cap;
    st.size = 0;
    return st;
  }
  // keeps `stores` while the pool holds at most `max_blocks` in all (the rest are freed)
  void give(std::vector<AlphaStore>& stores, size_t max_blocks) {
    std::lock_guard<std::mutex> lock(mu_);
    for (AlphaStore& st : stores)
      if (st.cap > 0 && kept_ + st.cap <= max_blocks) {
        kept_ += st.cap;
        free_.push_back(std::move(st));
      }
    stores.clear();
  }

 private:
  std::mutex mu_;
  std::vector<AlphaStore> free_;
  size_t kept_ = 0;  // blocks held by free_
};

}  // namespace
