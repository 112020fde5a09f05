// The persistent thread pool shared by slamkit's compiled CPU kernels (rasteriser, fused loss).
// A header in slamkit/csrc, which slamkit.native puts on every library's include path (and in its
// build hash); each library gets its own pool (anonymous namespace).
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include <unistd.h>

namespace {

// A persistent pool of worker threads. A job is a number of chunks handed out dynamically; the
// caller works too and waits only for chunks that were taken, never for a worker to start: on
// a busy machine (tracking beside mapping, other processes) a worker that is not scheduled in
// time is simply not waited for. One job at a time; a caller that finds the pool busy (renders
// from several Python threads) does its job alone.
class Pool {
 public:
  static Pool& instance() {
    static std::mutex m;
    static Pool* pool = nullptr;
    static int64_t pid = -1;
    std::lock_guard<std::mutex> lock(m);
    const int64_t now = (int64_t)::getpid();
    if (pool == nullptr || pid != now) {  // a forked child has none of the parent's threads
      pool = new Pool();  // never destroyed: its detached threads live as long as the process
      pid = now;
    }
    return *pool;
  }

  // f(chunk, worker) for every chunk in [0, chunks), worker in [0, nthreads) (0 = the caller)
  void run(int nthreads, int64_t chunks, const std::function<void(int64_t, int)>& f) {
    std::unique_lock<std::mutex> busy(run_mutex_, std::try_to_lock);
    if (nthreads <= 1 || chunks <= 1 || !busy.owns_lock()) {
      for (int64_t c = 0; c < chunks; ++c) f(c, 0);
      return;
    }
    ensure_workers(nthreads - 1);
    Job job;
    job.f = &f;
    job.chunks = chunks;
    job.max_workers = nthreads - 1;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      job.generation = ++generation_;
      job_ = &job;
    }
    wake_.notify_all();
    work(job, 0);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      job_ = nullptr;  // no worker joins from now on
    }
    std::unique_lock<std::mutex> lock(done_mutex_);
    done_.wait(lock, [&] { return job.active.load() == 0; });  // chunks taken by workers are finished
    if (job.error) std::rethrow_exception(job.error);
  }

 private:
  struct Job {
    const std::function<void(int64_t, int)>* f = nullptr;
    int64_t chunks = 0, generation = 0;
    int max_workers = 0;
    std::atomic<int64_t> next{0};
    std::atomic<int> active{0}, joined{0};
    std::mutex error_mutex;
    std::exception_ptr error;
  };

  static void work(Job& job, int worker) {
    for (;;) {
      const int64_t c = job.next.fetch_add(1, std::memory_order_relaxed);
      if (c >= job.chunks) return;
      try {
        (*job.f)(c, worker);
      } catch (...) {
        std::lock_guard<std::mutex> lock(job.error_mutex);
        if (!job.error) job.error = std::current_exception();
        job.next.store(job.chunks);  // stop handing out chunks
      }
    }
  }

  void ensure_workers(int n) {
    std::lock_guard<std::mutex> lock(mutex_);
    while (num_workers_ < n) {
      try {
        std::thread([this] { worker_loop(); }).detach();
      } catch (...) {  // no more threads: the caller (and the workers there are) do the work
        return;
      }
      ++num_workers_;
    }
  }

  void worker_loop() {
    int64_t seen = 0;
    for (;;) {
      Job* job;
      int id;
      {
        std::unique_lock<std::mutex> lock(mutex_);
        wake_.wait(lock, [&] { return job_ != nullptr && job_->generation != seen; });
        job = job_;
        seen = job->generation;
        id = job->joined.fetch_add(1) + 1;
        if (id > job->max_workers) continue;
        job->active.fetch_add(1);
      }
      work(*job, id);
      {
        std::lock_guard<std::mutex> lock(done_mutex_);
        job->active.fetch_sub(1);
      }
      done_.notify_all();
    }
  }

  std::mutex run_mutex_, mutex_, done_mutex_;
  std::condition_variable wake_, done_;
  Job* job_ = nullptr;
  int64_t generation_ = 0;
  int num_workers_ = 0;
};

// f(begin, end, worker) over [0, n) in chunks of `grain`, handed out dynamically to at most
// nthreads threads; worker < nthreads.
template <class F>
void parallel_for(int nthreads, int64_t n, int64_t grain, F&& f) {
  if (n <= 0) return;
  grain = std::max<int64_t>(grain, 1);
  const int64_t chunks = (n + grain - 1) / grain;
  const std::function<void(int64_t, int)> body = [&](int64_t c, int worker) {
    const int64_t b = c * grain;
    f(b, std::min(n, b + grain), worker);
  };
  Pool::instance().run((int)std::min<int64_t>(nthreads, chunks), chunks, body);
}

}  // namespace
