// What one core's float32 AVX2 + FMA units deliver at best: the fused decoder's own register block
// (gemm_block<3, 4> of csrc/mlp_f32_kernels.h, included here as csrc/mlp_f32.cpp includes it: 4 rows x
// 24 outputs, 12 ymm accumulators) run over data that stays in L1, on every core at once. The
// decoder's kernels cannot run faster than this.
//
//   g++ -O3 -fopenmp -o /tmp/fma_peak docs/benchmark/avx2-decoder/fma_peak.cpp && /tmp/fma_peak
#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <vector>

// What the kernels' header takes from the file that includes it (csrc/mlp_f32.cpp, csrc/mlp_common.h).
constexpr int64_t kTile = 64;
struct Layer {
  int64_t in_padded;
  int64_t out_padded;
  bool relu;
};
struct TileScratch {
  std::vector<float> dz, da;
};
typedef float V8 __attribute__((vector_size(32)));
typedef float V8u __attribute__((vector_size(32), aligned(4), may_alias));

#pragma GCC push_options
#pragma GCC target("avx2,fma")
namespace avx2 {
#include "../../../scalar_nerfstudio/csrc/mlp_f32_kernels.h"
}  // namespace avx2

// One 64 x 64 tile through the 4 x 24 block: C = relu(init + A B), rows 4 at a time (outputs 0-23).
__attribute__((noinline)) void tile(const float* a, const float* b, const float* init, float* c) {
  for (int64_t row = 0; row < kTile; row += 4)
    avx2::gemm_block<3, 4>(a + row * 64, 64, b, 64, 64, init, 0, true, c + row * 64, 64);
}

// One 64 x 64 tile's weight gradient, as the backward computes it: grad_wt [64, 64] += A^T Z.
__attribute__((noinline)) void weight_grad_tile(const float* z, const float* a, float* grad_wt) {
  avx2::weight_grad(z, a, 64, 64, grad_wt);
}
#pragma GCC pop_options

// GFLOP/s of one thread running the block over a 64 x 64 tile `reps` times.
static double one_thread(int reps) {
  std::vector<float> a(64 * 64, 0.5f), b(64 * 64, 0.25f), c(64 * 64), init(64, 0.0f);
  const auto start = std::chrono::steady_clock::now();
  for (int r = 0; r < reps; ++r) tile(a.data(), b.data(), init.data(), c.data());
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (c[5] != 8.0f) std::printf("unexpected result %f\n", c[5]);
  return 2.0 * reps * 16 * 4 * 24 * 64 / seconds / 1e9;
}

// GFLOP/s of one thread computing the weight gradient of a 64 x 64 layer over one tile `reps` times.
static double weight_grad_one_thread(int reps) {
  std::vector<float> z(64 * 64, 0.5f), a(64 * 64, 0.25f), grad_wt(64 * 64, 0.0f);
  const auto start = std::chrono::steady_clock::now();
  for (int r = 0; r < reps; ++r) weight_grad_tile(z.data(), a.data(), grad_wt.data());
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (grad_wt[3] != 8.0f * reps) std::printf("unexpected result %f\n", grad_wt[3]);
  return 2.0 * reps * 64 * 64 * 64 / seconds / 1e9;
}

int main() {
  const int reps = 200000;
  std::printf("weight gradient alone, one thread: %.1f GFLOP/s\n", weight_grad_one_thread(reps / 2));
  std::printf("one thread alone: %.1f GFLOP/s\n", one_thread(reps));
  double total = 0.0;
#pragma omp parallel reduction(+ : total)
  total += one_thread(reps);
  std::printf("%d threads at once: %.1f GFLOP/s in all\n", omp_get_max_threads(), total);
  return 0;
}
