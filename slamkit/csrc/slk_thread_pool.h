// The persistent thread pools shared by slamkit's compiled CPU kernels (rasteriser, fused loss).
// A header in slamkit/csrc, which slamkit.native puts on every library's include path (and in its
// build hash); each library gets its own pools (anonymous namespace).
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include <cerrno>
#include <utility>

#include <sched.h>
#include <sys/resource.h>
#include <unistd.h>

namespace {

// A thread's scheduling class on Linux: its policy (SCHED_OTHER, SCHED_BATCH, SCHED_IDLE) and
// nice value, both per thread there. A pool's workers keep the class of the threads they serve.
struct SchedClass {
  int policy = 0, nice = 0;

  static SchedClass of_calling_thread() {
    SchedClass c;
#ifdef __linux__
    c.policy = ::sched_getscheduler(0);
    errno = 0;
    const int nice = ::getpriority(PRIO_PROCESS, 0);  // Linux: the calling thread's
    c.nice = errno == 0 ? nice : 0;
#endif
    return c;
  }

  // Give the calling thread this class (a worker, once, when it starts; it already inherited it
  // from the caller that started it, unless that caller asked for SCHED_RESET_ON_FORK).
  void apply() const {
#ifdef __linux__
    if (policy == SCHED_OTHER || policy == SCHED_BATCH || policy == SCHED_IDLE) {
      sched_param param{};
      ::sched_setscheduler(0, policy, &param);
    }
    ::setpriority(PRIO_PROCESS, 0, nice);
#endif
  }

  bool operator==(const SchedClass& o) const { return policy == o.policy && nice == o.nice; }
};

// A persistent pool of worker threads. A job is a number of chunks handed out dynamically; the
// caller works too and waits only for chunks that were taken, never for a worker to start: on
// a busy machine (tracking beside mapping, other processes) a worker that is not scheduled in
// time is simply not waited for. One job at a time; a caller that finds the pool busy (renders
// from several Python threads) does its job alone.
//
// There is one pool per scheduling class of the calling threads: a job runs only on workers of
// its caller's priority, so a real-time mapping thread at a lower priority (slamkit.scheduling)
// has its renders done by workers at that priority too, whoever started a pool first, and the
// tracking side's jobs never wait for a worker of the mapper's lower priority.
class Pool {
 public:
  static Pool& instance() {
    static std::mutex m;
    static std::vector<std::pair<SchedClass, Pool*>> pools;
    static int64_t pid = -1;
    const SchedClass cls = SchedClass::of_calling_thread();
    std::lock_guard<std::mutex> lock(m);
    const int64_t now = (int64_t)::getpid();
    if (pid != now) {  // a forked child has none of the parent's threads
      pools.clear();  // (their memory is lost: never destroyed, as below)
      pid = now;
    }
    for (auto& entry : pools)
      if (entry.first == cls) return *entry.second;
    // never destroyed: its detached threads live as long as the process
    pools.emplace_back(cls, new Pool(cls));
    return *pools.back().second;
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

  explicit Pool(SchedClass cls) : class_(cls) {}

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
    class_.apply();
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

  const SchedClass class_;
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
