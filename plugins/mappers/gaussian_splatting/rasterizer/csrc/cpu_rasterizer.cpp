// slamkit CPU rasteriser: tile-based differentiable 3D Gaussian Splatting, forward and backward.
//
// Plain C++17 with a C ABI (loaded with ctypes by slamkit_plugins/mappers/gaussian_splatting/rasterizer/cpu_rasterizer.py):
// no torch headers, so it builds in seconds with any C++17 compiler and does not depend on the
// torch version (GCC >= 9 or Clang; vector extensions). Threads: a persistent pool, work handed
// out dynamically in chunks; results are independent of the thread count (every sum has a
// fixed order). One translation unit, its parts in the headers beside it, in the order they
// build on each other: conventions.h (the constants of the conventions below), projection.h (3D -> 2D and its
// backward), splats.h (a projected Gaussian on a tile's rows), alpha_store.h (the alphas kept
// for the backward), render_state.h (what a render keeps between its passes), composite.h (a
// tile's compositing: a chunk's visits and the tile's state), forward.h, backward.h; this file
// is the C ABI.
//
// Conventions: exactly those of slamkit.map.rendering.Rasterizer and the `torch` backend
// (plugins/mappers/gaussian_splatting/rasterizer/torch_rasterizer.py), which is the reference:
//   - p = R m + t; culled when p_z <= 0.01 or opacity <= 1/255 (float32 compare);
//   - u = fx x / z + cx, v = fy y / z + cy; J with x/z, y/z clamped to the image extended by
//     15 % (+0.5 px) on each side; 2D covariance J R Sigma R^T J^T + 0.3 I; conic = its inverse;
//   - a Gaussian covers, row by row, exactly the columns the torch backend's closed-form
//     interval gives (the same float32 operations in the same order: compiled with
//     -ffp-contract=off and without -ffast-math so they are reproduced bit for bit);
//   - log alpha = log o - q / 2, alpha = min(0.99, exp(log alpha));
//   - per pixel, front to back by camera z (ties by index); stop at the first Gaussian that
//     would bring the transmittance below 1e-4;
//   - colour = sum w c + (1 - sum w) bg, depth = sum w z, alpha = sum w, w = alpha T (the
//     background's weight is computed as the final transmittance, equal to 1 - sum w).
// The projection (means, quats, scales -> 2D mean, conic) and its backward are computed in
// double precision, four Gaussians at a time (the same operations in the same order as for one,
// so the same bits); the pixel work in float32 (16 pixels per vector, slamkit/csrc/slk_vec16.h),
// the per-Gaussian gradient sums in double.
//
// Forward: project + cull (parallel over Gaussians) -> radix sort by depth -> binning into
// 16x16 tiles (each Gaussian is listed, in depth order, in the tiles its exact row intervals
// touch) -> per tile, 64 entries at a time: their row spans (16 rows at once) and the blocks
// they cover (a block: a tile row of 16 pixels = one vector with AVX-512, else each 8-pixel half
// of it), then the alphas of all those (entry, block) visits, four at a time, then each block
// composited through its visits in depth order with its state in registers; per-pixel early
// termination, per-block and per-tile early exit. Kept for the backward pass: the final
// transmittance and the last composited list position of every pixel, each entry's blocks and
// span starts, and (when a backward pass follows) the visits' alphas (AlphaStore).
// Backward: per tile, the list walked back to front (the stored alphas; transmittance recovered
// by division, the suffix sum sum_{j>i} w_j v_j carried per pixel), per (tile, Gaussian) entry ten moments
// accumulated in registers and stored in that entry's own slot (no atomics); then per Gaussian
// the slots are reduced in a fixed order (deterministic) and the projection's analytic backward
// gives the gradients w.r.t. means, quaternions, scales, opacities and colours.

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <exception>

#include "forward.h"
#include "backward.h"
#include "render_state.h"

namespace {

constexpr int ABI_VERSION = 5;

void write_error(char* err, int errlen, const char* msg) {
  if (err && errlen > 0) std::snprintf(err, (size_t)errlen, "%s", msg);
}

}  // namespace

// ------------------------------------------------------------------------------------------
// C ABI. All arrays are contiguous float32 (viewmat, intrinsics float64); every output array
// is written in full. Functions return 0 / a handle, or -1 / NULL with a message in err.

extern "C" {

int slk_abi_version() { return ABI_VERSION; }

// alpha_bytes: how much of its alphas the forward pass may keep for a backward pass (AlphaStore;
// all threads together; 0 where no backward follows, or to have the backward recompute them)
void* slk_forward(int N, const float* means, const float* quats, const float* scales, const float* opac,
                  const float* colors, const double* viewmat, const double* intr, int W, int H, const float* bg,
                  int nthreads, int64_t alpha_bytes, float* out_color, float* out_depth, float* out_alpha,
                  int64_t* stats, char* err, int errlen) {
  State* S = nullptr;
  try {
    S = new State();
    S->N = N;
    S->W = W;
    S->H = H;
    S->tiles_x = (W + TILE - 1) / TILE;
    S->tiles_y = (H + TILE - 1) / TILE;
    S->cam = make_camera(viewmat, intr, W, H);
    S->alpha_budget = (size_t)std::max<int64_t>(alpha_bytes, 0) / sizeof(vblock) / std::max(1, nthreads);
    forward(*S, means, quats, scales, opac, colors, bg, std::max(1, nthreads), out_color, out_depth, out_alpha);
    stats[0] = S->num_pairs;
    stats[1] = S->M;
    stats[2] = (int64_t)S->tile_ids.size();
    stats[3] = S->num_rows;
    stats[4] = S->threads_used;
    stats[5] = S->num_rows_stored;
    return S;
  } catch (const std::exception& e) {
    write_error(err, errlen, e.what());
  } catch (...) {
    write_error(err, errlen, "unknown error");
  }
  delete S;
  return nullptr;
}

int slk_backward(void* state, const float* means, const float* quats, const float* scales, const float* opac,
                 const float* g_color, const float* g_depth, const float* g_alpha, const float* bg, int nthreads,
                 float* g_means, float* g_quats, float* g_scales, float* g_opac, float* g_colors, float* g_bg,
                 char* err, int errlen) {
  try {
    State& S = *static_cast<State*>(state);
    backward(S, means, quats, scales, opac, g_color, g_depth, g_alpha, bg, std::max(1, nthreads), g_means, g_quats,
             g_scales, g_opac, g_colors, g_bg);
    return 0;
  } catch (const std::exception& e) {
    write_error(err, errlen, e.what());
  } catch (...) {
    write_error(err, errlen, "unknown error");
  }
  return -1;
}

// per-phase wall (out[0:8]) and process CPU (out[8:16]) microseconds of the last passes
void slk_times(void* state, int64_t* out) {
  const State& S = *static_cast<const State*>(state);
  for (int i = 0; i < 8; ++i) {
    out[i] = S.wall_us[i];
    out[8 + i] = S.cpu_us[i];
  }
}

void slk_free(void* state) { delete static_cast<State*>(state); }

}  // extern "C"
