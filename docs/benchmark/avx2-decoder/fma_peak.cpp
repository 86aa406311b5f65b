// What one core's float32 AVX2 + FMA units deliver at best: the fused decoder's own register block
// (csrc/mlp_f32_kernels.h, gemm_block<3, 4>: 4 rows x 24 outputs, 12 ymm accumulators) run over
// data that stays in L1, on every core at once. The decoder's kernels cannot run faster than this.
//
//   g++ -O3 -fopenmp -o /tmp/fma_peak docs/benchmark/avx2-decoder/fma_peak.cpp && /tmp/fma_peak
#include <omp.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <vector>

#pragma GCC target("avx2,fma")

typedef float V8 __attribute__((vector_size(32)));
typedef float V8u __attribute__((vector_size(32), aligned(4), may_alias));

static inline V8 load8(const float* p) { return *reinterpret_cast<const V8u*>(p); }
static inline void store8(float* p, V8 v) { *reinterpret_cast<V8u*>(p) = v; }

// C[R, OB * 8] = A[R, K] B[K, OB * 8], A and C with row stride `stride`.
template <int OB, int R>
__attribute__((noinline)) void block(const float* a, const float* b, int64_t k_count, int64_t stride, float* c) {
  V8 acc[R][OB] = {};
  for (int64_t k = 0; k < k_count; ++k) {
    V8 w[OB];
    for (int j = 0; j < OB; ++j) w[j] = load8(b + k * stride + j * 8);
    for (int i = 0; i < R; ++i) {
      const float x = a[i * stride + k];
      const V8 xv = {x, x, x, x, x, x, x, x};
      for (int j = 0; j < OB; ++j) acc[i][j] += xv * w[j];
    }
  }
  for (int i = 0; i < R; ++i)
    for (int j = 0; j < OB; ++j) store8(c + i * stride + j * 8, acc[i][j]);
}

// GFLOP/s of one thread running the 4 x 24 block over a 64 x 64 tile `reps` times.
static double one_thread(int reps) {
  std::vector<float> a(64 * 64, 0.5f), b(64 * 64, 0.25f), c(64 * 64);
  const auto start = std::chrono::steady_clock::now();
  for (int r = 0; r < reps; ++r)
    for (int row = 0; row < 64; row += 4) block<3, 4>(a.data() + row * 64, b.data(), 64, 64, c.data() + row * 64);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (c[5] != 8.0f) std::printf("unexpected result %f\n", c[5]);
  return 2.0 * reps * 16 * 4 * 24 * 64 / seconds / 1e9;
}

int main() {
  const int reps = 200000;
  std::printf("one thread alone: %.1f GFLOP/s\n", one_thread(reps));
  double total = 0.0;
#pragma omp parallel reduction(+ : total)
  total += one_thread(reps);
  std::printf("%d threads at once: %.1f GFLOP/s in all\n", omp_get_max_threads(), total);
  return 0;
}
