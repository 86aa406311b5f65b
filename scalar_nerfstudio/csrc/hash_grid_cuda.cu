// Multi-resolution hash-grid encoding (Instant-NGP style), CUDA kernels.
//
// Registered as torch ops `torch.ops.scalar_nerf_hash_grid_cuda.forward` / `.backward`; the Python
// side (scalar_nerfstudio/encodings/hash_grid.py) wraps them in an autograd.Function. Built on first
// use on a CUDA tensor (scalar_nerfstudio/encodings/_cpp.py); importing the package never builds it.
//
// Semantics: exactly those of csrc/hash_grid.cpp and `reference_hash_encoding` (see the module
// docstring of hash_grid.py): NaN -> 0 and clamping to [0, 1]; pos = p * R_l in float32 (written
// with __fmul_rn, and the extension is built with --fmad=false, so that no product is fused into a
// sum: the float32 results are those of the C++ kernel);
// cell = min(floor(pos), R_l - 1); weights (wx * wy) * wz; dense rows x + y (R+1) + z (R+1)^2,
// hashed rows (x ^ y * 2654435761 ^ z * 805459861) & (T - 1) in uint32 arithmetic.
//
// Why a kernel: the torch implementation takes about ten small kernels per level and pass (16
// levels, forward and backward), and a training step on an H200 was two-thirds launch overhead
// (docs/notebook/defaults.md, "On a GPU"). Here a pass is one launch: one thread per (point, level),
// levels on the grid's y axis. The backward adds each corner's share with atomicAdd, so the
// order of the float32 sums (and the last bits of the gradient) can vary between runs.

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <cuda_runtime.h>

#include <cstdint>
#include <vector>

#include "check.h"
#include "hash_grid_checks.h"

namespace {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;
constexpr int kMaxLevels = 32;
constexpr int kThreads = 256;

// Geometry of every level, passed by value to the kernels (kernel parameters live in constant
// memory, so every thread reads them at no cost).
struct Levels {
  int64_t offset[kMaxLevels];  // first row of the level in the flat table
  float scale[kMaxLevels];     // R_l as float32 (exact: R_l < 2^24 is checked)
  int32_t res[kMaxLevels];     // R_l
  uint32_t stride[kMaxLevels]; // R_l + 1
  bool dense[kMaxLevels];
  uint32_t mask;               // T - 1
  int32_t count;               // L
};

// Cell index and fractional position of coordinate v along one axis.
__device__ __forceinline__ void axis(float v, float scale, int32_t res, uint32_t& cell, float& frac) {
  const float clamped = v >= 0.0f ? (v <= 1.0f ? v : 1.0f) : 0.0f;  // NaN -> 0, +-inf -> 1 / 0
  const float scaled = __fmul_rn(clamped, scale);
  const int32_t fl = min(static_cast<int32_t>(scaled), res - 1);  // scaled >= 0: truncation is floor
  cell = static_cast<uint32_t>(fl);
  frac = scaled - static_cast<float>(fl);
}

// Rows (absolute, in the flat table) and weights of the 8 corners of point p on level l.
__device__ __forceinline__ void corners(const float* __restrict__ p, const Levels& lv, int l, int64_t row[8],
                                        float weight[8]) {
  uint32_t cx, cy, cz;
  float fx, fy, fz;
  axis(p[0], lv.scale[l], lv.res[l], cx, fx);
  axis(p[1], lv.scale[l], lv.res[l], cy, fy);
  axis(p[2], lv.scale[l], lv.res[l], cz, fz);
  const float wx[2] = {1.0f - fx, fx};
  const float wy[2] = {1.0f - fy, fy};
  const float wz[2] = {1.0f - fz, fz};
  const bool dense = lv.dense[l];
  const uint32_t my = dense ? lv.stride[l] : kPrimeY;
  const uint32_t mz = dense ? lv.stride[l] * lv.stride[l] : kPrimeZ;
  const uint32_t hy[2] = {cy * my, (cy + 1) * my};
  const uint32_t hz[2] = {cz * mz, (cz + 1) * mz};
#pragma unroll
  for (int k = 0; k < 2; ++k) {
#pragma unroll
    for (int j = 0; j < 2; ++j) {
#pragma unroll
      for (int i = 0; i < 2; ++i) {
        const int c = i + 2 * j + 4 * k;
        const uint32_t x = cx + i;
        const uint32_t r = dense ? x + hy[j] + hz[k] : (x ^ hy[j] ^ hz[k]) & lv.mask;
        row[c] = lv.offset[l] + static_cast<int64_t>(r);
        weight[c] = __fmul_rn(__fmul_rn(wx[i], wy[j]), wz[k]);
      }
    }
  }
}

// out[n, l * F + f] = feature f of point n on level l = blockIdx.y.
template <int F>
__global__ void forward_kernel(const float* __restrict__ positions, const float* __restrict__ table,
                               float* __restrict__ out, int64_t n, const Levels levels) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const int l = blockIdx.y;
  if (i >= n) return;
  int64_t row[8];
  float weight[8];
  corners(positions + 3 * i, levels, l, row, weight);
  float acc[F];
#pragma unroll
  for (int f = 0; f < F; ++f) acc[f] = 0.0f;
#pragma unroll
  for (int c = 0; c < 8; ++c) {
    const float* r = table + row[c] * F;
#pragma unroll
    for (int f = 0; f < F; ++f) acc[f] += weight[c] * __ldg(r + f);
  }
  float* o = out + i * (static_cast<int64_t>(levels.count) * F) + l * F;
#pragma unroll
  for (int f = 0; f < F; ++f) o[f] = acc[f];
}

// grad_table[row] += weight * grad_out[n, l * F + f] over the 8 corners of point n on level l.
template <int F>
__global__ void backward_kernel(const float* __restrict__ positions, const float* __restrict__ grad_out,
                                float* __restrict__ grad_table, int64_t n, const Levels levels) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const int l = blockIdx.y;
  if (i >= n) return;
  const float* g = grad_out + i * (static_cast<int64_t>(levels.count) * F) + l * F;
  float gv[F];
  bool any = false;
#pragma unroll
  for (int f = 0; f < F; ++f) {
    gv[f] = g[f];
    any = any || gv[f] != 0.0f;
  }
  if (!any) return;  // e.g. samples the renderer gave no weight: nothing to add
  int64_t row[8];
  float weight[8];
  corners(positions + 3 * i, levels, l, row, weight);
#pragma unroll
  for (int c = 0; c < 8; ++c) {
    float* r = grad_table + row[c] * F;
#pragma unroll
    for (int f = 0; f < F; ++f) atomicAdd(r + f, weight[c] * gv[f]);
  }
}

constexpr const char* kWho = "hash_grid cuda";

// Per-level geometry of the kernels, from the checked layout (hash_grid_checks.h).
Levels make_levels(at::IntArrayRef level_offsets, at::IntArrayRef resolutions, int64_t hashmap_size,
                   int64_t table_rows) {
  const int64_t num_levels = static_cast<int64_t>(resolutions.size());
  SCALAR_CHECK(num_levels <= kMaxLevels, kWho, ": at most ", kMaxLevels, " levels, got ", num_levels);
  const std::vector<scalar_nerf::LevelSpec> specs =
      scalar_nerf::level_specs(level_offsets, resolutions, hashmap_size, table_rows, kWho);
  Levels levels{};
  levels.mask = static_cast<uint32_t>(hashmap_size - 1);
  levels.count = static_cast<int32_t>(num_levels);
  for (int64_t l = 0; l < num_levels; ++l) {
    const scalar_nerf::LevelSpec& spec = specs[l];
    levels.offset[l] = spec.offset;
    levels.scale[l] = static_cast<float>(spec.res);
    levels.res[l] = static_cast<int32_t>(spec.res);
    levels.stride[l] = static_cast<uint32_t>(spec.res + 1);
    levels.dense[l] = spec.dense;
  }
  return levels;
}

void check_launch(const char* what) {
  const cudaError_t err = cudaGetLastError();
  SCALAR_CHECK(err == cudaSuccess, kWho, ": ", what, " failed to launch: ", cudaGetErrorString(err));
}

dim3 grid_for(int64_t n, int num_levels) {
  return dim3(static_cast<unsigned int>((n + kThreads - 1) / kThreads), static_cast<unsigned int>(num_levels));
}

// positions [N, 3], table [rows, F] -> features [N, L * F] (level l in columns l*F .. l*F+F-1).
at::Tensor hash_grid_forward(const at::Tensor& positions, const at::Tensor& table, at::IntArrayRef level_offsets,
                             at::IntArrayRef resolutions, int64_t hashmap_size) {
  const int64_t f = scalar_nerf::check_forward_call(positions, table, /*cuda=*/true, kWho);
  const Levels levels = make_levels(level_offsets, resolutions, hashmap_size, table.size(0));
  const int64_t n = positions.size(0);
  SCALAR_CHECK(n < (int64_t{1} << 31) * kThreads, kWho, ": too many points: ", n);
  at::Tensor out = at::empty({n, static_cast<int64_t>(levels.count) * f}, positions.options());
  if (n == 0) return out;
  const c10::cuda::CUDAGuard guard(positions.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const float* pos = positions.data_ptr<float>();
  const float* tab = table.data_ptr<float>();
  float* o = out.data_ptr<float>();
  const dim3 grid = grid_for(n, levels.count);
  switch (f) {
    case 1: forward_kernel<1><<<grid, kThreads, 0, stream>>>(pos, tab, o, n, levels); break;
    case 2: forward_kernel<2><<<grid, kThreads, 0, stream>>>(pos, tab, o, n, levels); break;
    case 4: forward_kernel<4><<<grid, kThreads, 0, stream>>>(pos, tab, o, n, levels); break;
    default: forward_kernel<8><<<grid, kThreads, 0, stream>>>(pos, tab, o, n, levels); break;
  }
  check_launch("forward");
  return out;
}

// grad_out [N, L * F], positions [N, 3] -> gradient of the table [rows, F].
at::Tensor hash_grid_backward(const at::Tensor& grad_out, const at::Tensor& positions, at::IntArrayRef level_offsets,
                              at::IntArrayRef resolutions, int64_t hashmap_size, int64_t features_per_level) {
  const int64_t f = features_per_level;
  const int64_t table_rows = scalar_nerf::check_backward_call(
      grad_out, positions, level_offsets, static_cast<int64_t>(resolutions.size()), f, /*cuda=*/true, kWho);
  const int64_t n = positions.size(0);
  const Levels levels = make_levels(level_offsets, resolutions, hashmap_size, table_rows);
  SCALAR_CHECK(n < (int64_t{1} << 31) * kThreads, kWho, ": too many points: ", n);
  at::Tensor grad_table = at::zeros({table_rows, f}, grad_out.options());
  if (n == 0) return grad_table;
  const c10::cuda::CUDAGuard guard(positions.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const float* pos = positions.data_ptr<float>();
  const float* g = grad_out.data_ptr<float>();
  float* gt = grad_table.data_ptr<float>();
  const dim3 grid = grid_for(n, levels.count);
  switch (f) {
    case 1: backward_kernel<1><<<grid, kThreads, 0, stream>>>(pos, g, gt, n, levels); break;
    case 2: backward_kernel<2><<<grid, kThreads, 0, stream>>>(pos, g, gt, n, levels); break;
    case 4: backward_kernel<4><<<grid, kThreads, 0, stream>>>(pos, g, gt, n, levels); break;
    default: backward_kernel<8><<<grid, kThreads, 0, stream>>>(pos, g, gt, n, levels); break;
  }
  check_launch("backward");
  return grad_table;
}

}  // namespace

TORCH_LIBRARY(scalar_nerf_hash_grid_cuda, m) {
  m.def("forward(Tensor positions, Tensor table, int[] level_offsets, int[] resolutions, int hashmap_size) -> Tensor",
        &hash_grid_forward);
  m.def(
      "backward(Tensor grad_out, Tensor positions, int[] level_offsets, int[] resolutions, int hashmap_size, "
      "int features_per_level) -> Tensor",
      &hash_grid_backward);
}
