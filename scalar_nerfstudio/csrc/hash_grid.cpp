// Multi-resolution hash-grid encoding (Instant-NGP style), CPU kernels with OpenMP.
//
// Registered as torch ops `torch.ops.scalar_nerf_hash_grid.forward` / `.backward`; the Python
// side (scalar_nerfstudio/encodings/hash_grid.py) wraps them in an autograd.Function.
//
// Semantics (identical to `reference_hash_encoding` in hash_grid.py):
//   * each coordinate of a point is sanitised: NaN -> 0, then clamped to [0, 1];
//   * level l has resolution R_l; pos = p * R_l (float32), cell = min(floor(pos), R_l - 1),
//     frac = pos - cell; the 8 corners cell + {0,1}^3 are blended with trilinear weights
//     w = (wx * wy) * wz, wx in {1 - frac_x, frac_x} (same for y, z);
//   * dense level ((R_l + 1)^3 <= T): row = x + y * (R_l + 1) + z * (R_l + 1)^2;
//     hashed level: row = (x ^ y * 2654435761 ^ z * 805459861) & (T - 1) in uint32 arithmetic;
//   * rows are relative to the level's block starting at level_offsets[l] in the flat table.
//
// Performance (the loops are bound by the latency of random table accesses):
//   * level-major: all points go through one level before the next, so that level's table
//     (<= T rows) stays cache-hot;
//   * each point's 8 corners are computed once, kPrefetchDistance points ahead of their use,
//     and their table rows are prefetched then;
//   * forward: points are split statically over at::get_num_threads() OpenMP threads;
//   * backward: levels are distributed over the threads (largest first), so each gradient row
//     has exactly one writer: no atomics, no per-thread gradient copies, and results that do not
//     depend on the thread count;
//   * outputs are allocated huge-page backed and aligned (see empty_huge_paged).

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/from_blob.h>
#include <c10/util/accumulate.h>
#include <torch/library.h>

#include "check.h"
#include "hash_grid_checks.h"

#include <omp.h>
#ifdef __linux__
#include <sys/mman.h>
#endif

#include <algorithm>
#include <cstdlib>
#include <cstdint>
#include <numeric>
#include <vector>

namespace {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;

// How many points ahead the loops compute corners and prefetch their table rows.
constexpr int64_t kPrefetchDistance = 16;

// Geometry of one level of the grid.
struct Level {
  float scale;      // R_l as float32 (exact: R_l < 2^24 is checked)
  int32_t res;      // R_l
  uint32_t stride;  // R_l + 1 (vertices per axis)
  uint32_t mask;    // T - 1
  int64_t offset;   // first row of this level in the flat table
  int64_t rows;     // rows of this level
  bool dense;
};

// Table rows (relative to the level's first row) and trilinear weights of the 8 corners of one
// point; corner c = i + 2 j + 4 k is cell + (i, j, k).
struct Corners {
  uint32_t row[8];
  float weight[8];
};

// Cell index and fractional position of coordinate v along one axis of level lv.
[[gnu::always_inline]] inline void axis(float v, const Level& lv, uint32_t& cell, float& frac) {
  const float clamped = v >= 0.0f ? (v <= 1.0f ? v : 1.0f) : 0.0f;  // NaN -> 0, +-inf -> 1 / 0
  const float scaled = clamped * lv.scale;
  // scaled >= 0, so truncation is floor (and much cheaper than std::floor without SSE4.1).
  const int32_t fl = std::min(static_cast<int32_t>(scaled), lv.res - 1);
  cell = static_cast<uint32_t>(fl);
  frac = scaled - static_cast<float>(fl);
}

// Corner rows and weights of point p (3 floats) on level lv.
template <bool Dense>
[[gnu::always_inline]] inline void corners(const float* p, const Level& lv, Corners& out) {
  uint32_t cx, cy, cz;
  float fx, fy, fz;
  axis(p[0], lv, cx, fx);
  axis(p[1], lv, cy, fy);
  axis(p[2], lv, cz, fz);
  const float wx[2] = {1.0f - fx, fx};
  const float wy[2] = {1.0f - fy, fy};
  const float wz[2] = {1.0f - fz, fz};
  const uint32_t my = Dense ? lv.stride : kPrimeY;
  const uint32_t mz = Dense ? lv.stride * lv.stride : kPrimeZ;
  const uint32_t hy[2] = {cy * my, (cy + 1) * my};
  const uint32_t hz[2] = {cz * mz, (cz + 1) * mz};
  for (int k = 0; k < 2; ++k) {
    for (int j = 0; j < 2; ++j) {
      const int c = 2 * j + 4 * k;
      if constexpr (Dense) {
        out.row[c] = cx + hy[j] + hz[k];
        out.row[c + 1] = (cx + 1) + hy[j] + hz[k];
      } else {
        out.row[c] = (cx ^ hy[j] ^ hz[k]) & lv.mask;
        out.row[c + 1] = ((cx + 1) ^ hy[j] ^ hz[k]) & lv.mask;
      }
      out.weight[c] = (wx[0] * wy[j]) * wz[k];
      out.weight[c + 1] = (wx[1] * wy[j]) * wz[k];
    }
  }
}

// Computes the corners of point i and prefetches its rows (for writing when ForWrite == 1).
template <int F, bool Dense, int ForWrite>
inline void prepare(const float* pos, const float* level_table, const Level& lv, int64_t i, Corners& cs) {
  corners<Dense>(pos + 3 * i, lv, cs);
  for (int c = 0; c < 8; ++c) {
    __builtin_prefetch(level_table + static_cast<int64_t>(cs.row[c]) * F, ForWrite, 1);
  }
}

// Calls visit(i, corners of i) for i in [begin, end); the corners of point i + kPrefetchDistance
// are computed and their rows prefetched right after point i is visited (a ring of corners).
template <int F, bool Dense, int ForWrite, typename Visit>
inline void for_each_point(const float* pos, const float* level_table, const Level& lv, int64_t begin, int64_t end,
                           Visit&& visit) {
  Corners ring[kPrefetchDistance];
  for (int64_t i = begin; i < std::min(end, begin + kPrefetchDistance); ++i) {
    prepare<F, Dense, ForWrite>(pos, level_table, lv, i, ring[i % kPrefetchDistance]);
  }
  for (int64_t i = begin; i < end; ++i) {
    Corners& cs = ring[i % kPrefetchDistance];
    visit(i, cs);
    if (i + kPrefetchDistance < end) {
      prepare<F, Dense, ForWrite>(pos, level_table, lv, i + kPrefetchDistance, cs);
    }
  }
}

// out[i * out_stride + f] = feature f of point i on level lv, for i in [begin, end).
template <int F, bool Dense>
void forward_level(const float* pos, const float* table, float* out, int64_t out_stride, const Level& lv,
                   int64_t begin, int64_t end) {
  const float* level_table = table + lv.offset * F;
  for_each_point<F, Dense, 0>(pos, level_table, lv, begin, end, [&](int64_t i, const Corners& cs) {
    float acc[F] = {};
    for (int c = 0; c < 8; ++c) {
      const float* row = level_table + static_cast<int64_t>(cs.row[c]) * F;
      const float w = cs.weight[c];
      for (int f = 0; f < F; ++f) acc[f] += w * row[f];
    }
    float* o = out + i * out_stride;
    for (int f = 0; f < F; ++f) o[f] = acc[f];
  });
}

// level_grad[row] += weight * grad_out[i * out_stride + f] over the corners of all n points on
// level lv.
template <int F, bool Dense>
void backward_level(const float* pos, const float* grad_out, float* level_grad, int64_t out_stride, const Level& lv,
                    int64_t n) {
  for_each_point<F, Dense, 1>(pos, level_grad, lv, 0, n, [&](int64_t i, const Corners& cs) {
    const float* g = grad_out + i * out_stride;
    float gv[F];
    for (int f = 0; f < F; ++f) gv[f] = g[f];
    for (int c = 0; c < 8; ++c) {
      float* row = level_grad + static_cast<int64_t>(cs.row[c]) * F;
      const float w = cs.weight[c];
      for (int f = 0; f < F; ++f) row[f] += w * gv[f];
    }
  });
}

// Features of all n points, level-major, points split statically over num_threads threads.
template <int F>
void forward_impl(const float* pos, const float* table, float* out, int64_t n, const std::vector<Level>& levels,
                  int num_threads) {
  const int64_t num_levels = static_cast<int64_t>(levels.size());
  const int64_t out_stride = num_levels * F;
#pragma omp parallel num_threads(num_threads)
  {
    const int t = omp_get_thread_num();
    const int threads = omp_get_num_threads();
    const int64_t begin = n * t / threads;
    const int64_t end = n * (t + 1) / threads;
    for (int64_t l = 0; l < num_levels; ++l) {
      const Level& lv = levels[l];
      if (lv.dense) {
        forward_level<F, true>(pos, table, out + l * F, out_stride, lv, begin, end);
      } else {
        forward_level<F, false>(pos, table, out + l * F, out_stride, lv, begin, end);
      }
    }
  }
}

// grad_table (zeroed on entry) += sum over points and corners of weight * grad_out. Levels are
// distributed over threads (largest first), so every row has exactly one writer: no atomics and
// no private buffers. At most num_levels threads are used.
template <int F>
void backward_impl(const float* pos, const float* grad_out, float* grad_table, int64_t n,
                   const std::vector<Level>& levels, int num_threads) {
  const int64_t num_levels = static_cast<int64_t>(levels.size());
  const int64_t out_stride = num_levels * F;
  std::vector<int64_t> order(num_levels);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(),
                   [&](int64_t a, int64_t b) { return levels[a].rows > levels[b].rows; });
  const int threads = static_cast<int>(std::min<int64_t>(num_threads, num_levels));
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int64_t k = 0; k < num_levels; ++k) {
    const int64_t l = order[k];
    const Level& lv = levels[l];
    float* level_grad = grad_table + lv.offset * F;
    if (lv.dense) {
      backward_level<F, true>(pos, grad_out + l * F, level_grad, out_stride, lv, n);
    } else {
      backward_level<F, false>(pos, grad_out + l * F, level_grad, out_stride, lv, n);
    }
  }
}

// An uninitialised float32 CPU tensor. On Linux, large ones (>= 2 MiB) are allocated 2 MiB-aligned
// and advised to use transparent huge pages before first touch: faulting tens of MB per call in
// 4 KiB pages costs a good fraction of the kernel time, and a fixed alignment of the strided output
// rows avoids 4K-aliasing stalls that otherwise depend on where malloc happens to place them.
at::Tensor empty_huge_paged(at::IntArrayRef sizes, const at::TensorOptions& options) {
#ifdef __linux__
  constexpr size_t kHugePage = size_t{1} << 21;
  const size_t nbytes = static_cast<size_t>(c10::multiply_integers(sizes)) * sizeof(float);
  if (nbytes >= kHugePage) {
    const size_t rounded = (nbytes + kHugePage - 1) & ~(kHugePage - 1);
    void* data = std::aligned_alloc(kHugePage, rounded);
    SCALAR_CHECK(data != nullptr, "hash_grid cpp: out of memory allocating ", rounded, " bytes");
    madvise(data, rounded, MADV_HUGEPAGE);  // advisory only; failure just means 4 KiB pages
    return at::from_blob(data, sizes, [](void* p) { std::free(p); }, options);
  }
#endif
  return at::empty(sizes, options);
}

constexpr const char* kWho = "hash_grid cpp";

// Per-level geometry of the kernel, from the checked layout (hash_grid_checks.h).
std::vector<Level> make_levels(at::IntArrayRef level_offsets, at::IntArrayRef resolutions, int64_t hashmap_size,
                               int64_t table_rows) {
  const std::vector<scalar_nerf::LevelSpec> specs =
      scalar_nerf::level_specs(level_offsets, resolutions, hashmap_size, table_rows, kWho);
  std::vector<Level> levels(specs.size());
  for (size_t l = 0; l < specs.size(); ++l) {
    const scalar_nerf::LevelSpec& spec = specs[l];
    Level& lv = levels[l];
    lv.scale = static_cast<float>(spec.res);
    lv.res = static_cast<int32_t>(spec.res);
    lv.dense = spec.dense;
    lv.stride = static_cast<uint32_t>(spec.res + 1);
    lv.mask = static_cast<uint32_t>(hashmap_size - 1);
    lv.offset = spec.offset;
    lv.rows = spec.rows;
  }
  return levels;
}

// Threads for n points: at most at::get_num_threads(), and at least ~1024 points per thread.
int num_threads_for(int64_t n) {
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), n / 1024)));
}

// positions [N, 3], table [rows, F] -> features [N, L * F] (level l in columns l*F .. l*F+F-1).
at::Tensor hash_grid_forward(const at::Tensor& positions, const at::Tensor& table, at::IntArrayRef level_offsets,
                             at::IntArrayRef resolutions, int64_t hashmap_size) {
  const int64_t f = scalar_nerf::check_forward_call(positions, table, /*cuda=*/false, kWho);
  const std::vector<Level> levels = make_levels(level_offsets, resolutions, hashmap_size, table.size(0));
  const int64_t n = positions.size(0);
  at::Tensor out = empty_huge_paged({n, static_cast<int64_t>(levels.size()) * f}, positions.options());
  if (n == 0) return out;
  const float* pos = positions.data_ptr<float>();
  const float* tab = table.data_ptr<float>();
  float* o = out.data_ptr<float>();
  const int nt = num_threads_for(n);
  switch (f) {
    case 1: forward_impl<1>(pos, tab, o, n, levels, nt); break;
    case 2: forward_impl<2>(pos, tab, o, n, levels, nt); break;
    case 4: forward_impl<4>(pos, tab, o, n, levels, nt); break;
    default: forward_impl<8>(pos, tab, o, n, levels, nt); break;
  }
  return out;
}

// grad_out [N, L * F], positions [N, 3] -> gradient of the table [rows, F].
at::Tensor hash_grid_backward(const at::Tensor& grad_out, const at::Tensor& positions, at::IntArrayRef level_offsets,
                              at::IntArrayRef resolutions, int64_t hashmap_size, int64_t features_per_level) {
  const int64_t f = features_per_level;
  const int64_t table_rows = scalar_nerf::check_backward_call(
      grad_out, positions, level_offsets, static_cast<int64_t>(resolutions.size()), f, /*cuda=*/false, kWho);
  const int64_t n = positions.size(0);
  const std::vector<Level> levels = make_levels(level_offsets, resolutions, hashmap_size, table_rows);
  at::Tensor grad_table = empty_huge_paged({table_rows, f}, grad_out.options());
  grad_table.zero_();
  if (n == 0) return grad_table;
  const float* pos = positions.data_ptr<float>();
  const float* g = grad_out.data_ptr<float>();
  float* gt = grad_table.data_ptr<float>();
  const int nt = num_threads_for(n);
  switch (f) {
    case 1: backward_impl<1>(pos, g, gt, n, levels, nt); break;
    case 2: backward_impl<2>(pos, g, gt, n, levels, nt); break;
    case 4: backward_impl<4>(pos, g, gt, n, levels, nt); break;
    default: backward_impl<8>(pos, g, gt, n, levels, nt); break;
  }
  return grad_table;
}

}  // namespace

TORCH_LIBRARY(scalar_nerf_hash_grid, m) {
  m.def("forward(Tensor positions, Tensor table, int[] level_offsets, int[] resolutions, int hashmap_size) -> Tensor",
        &hash_grid_forward);
  m.def(
      "backward(Tensor grad_out, Tensor positions, int[] level_offsets, int[] resolutions, int hashmap_size, "
      "int features_per_level) -> Tensor",
      &hash_grid_backward);
}
