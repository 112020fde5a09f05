// Adam over the rows of a Gaussian map with one step count per row, updating only the rows
// that have a non-zero gradient in some parameter (the "visible" rows of a training step).
// C ABI, loaded with ctypes by slamkit_plugins.mappers.gaussian_splatting.optimizer.visible_adam; float32 tensors,
// row-major, contiguous. Each row is updated exactly as Adam updates a parameter whose only
// steps are the ones in which it had a gradient (bias corrections from its own step count).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <thread>
#include <vector>

constexpr int ABI_VERSION = 3;
constexpr int MAX_PARAMS = 8;

struct Tensors {
  int count;                   // parameter tensors
  float* param[MAX_PARAMS];    // (rows, width)
  const float* grad[MAX_PARAMS];
  float* m[MAX_PARAMS];
  float* v[MAX_PARAMS];
  int width[MAX_PARAMS];
  float lr[MAX_PARAMS];
};

static bool row_seen(const Tensors& t, int64_t r) {
  for (int k = 0; k < t.count; ++k) {
    const float* g = t.grad[k] + r * t.width[k];
    for (int j = 0; j < t.width[k]; ++j)
      if (g[j] != 0.0f) return true;
  }
  return false;
}

// corrections[2 t], corrections[2 t + 1]: 1 - b1^t and 1 - b2^t for the step counts t in use.
// global_step > 0: every row is bias-corrected with that step count instead of its own.
static int64_t update_rows(const Tensors& t, float* steps, const float* corrections, int64_t global_step,
                           int64_t begin, int64_t end, float b1, float b2, float eps, bool only_visible) {
  int64_t updated = 0;
  for (int64_t r = begin; r < end; ++r) {
    if (only_visible && !row_seen(t, r)) continue;
    const float step = steps[r] + 1.0f;
    steps[r] = step;
    const int64_t ts = global_step > 0 ? global_step : (int64_t)step;
    const float c1 = corrections[2 * ts], c2 = corrections[2 * ts + 1];
    for (int k = 0; k < t.count; ++k) {
      const int w = t.width[k];
      float* p = t.param[k] + r * w;
      const float* g = t.grad[k] + r * w;
      float* m = t.m[k] + r * w;
      float* v = t.v[k] + r * w;
      for (int j = 0; j < w; ++j) {
        m[j] = b1 * m[j] + (1.0f - b1) * g[j];
        v[j] = b2 * v[j] + (1.0f - b2) * g[j] * g[j];
        p[j] -= t.lr[k] * ((m[j] / c1) / (std::sqrt(v[j] / c2) + eps));
      }
    }
    ++updated;
  }
  return updated;
}

extern "C" {

int slk_abi_version() { return ABI_VERSION; }

// Returns the number of rows updated. Rows are split into `nthreads` contiguous ranges.
// corrections: (max step count after this update + 1) x 2 bias corrections (see update_rows).
int64_t slk_visible_adam(int64_t rows, int count, float** param, const float** grad, float** m, float** v,
                         const int* width, const float* lr, float* steps, const float* corrections,
                         int64_t global_step, float b1, float b2, float eps, int only_visible, int nthreads) {
  Tensors t{};
  t.count = count < MAX_PARAMS ? count : MAX_PARAMS;
  for (int k = 0; k < t.count; ++k) {
    t.param[k] = param[k];
    t.grad[k] = grad[k];
    t.m[k] = m[k];
    t.v[k] = v[k];
    t.width[k] = width[k];
    t.lr[k] = lr[k];
  }
  if (nthreads <= 1 || rows < 65536) return update_rows(t, steps, corrections, global_step, 0, rows, b1, b2, eps, only_visible != 0);
  std::vector<int64_t> counts(nthreads, 0);
  std::vector<std::thread> workers;
  const int64_t chunk = (rows + nthreads - 1) / nthreads;
  for (int i = 1; i < nthreads; ++i) {
    const int64_t b = i * chunk, e = b + chunk < rows ? b + chunk : rows;
    if (b < e) workers.emplace_back([&, i, b, e] { counts[i] = update_rows(t, steps, corrections, global_step, b, e, b1, b2, eps, only_visible != 0); });
  }
  counts[0] = update_rows(t, steps, corrections, global_step, 0, chunk < rows ? chunk : rows, b1, b2, eps, only_visible != 0);
  for (auto& w : workers) w.join();
  int64_t total = 0;
  for (int64_t c : counts) total += c;
  return total;
}

}  // extern "C"
