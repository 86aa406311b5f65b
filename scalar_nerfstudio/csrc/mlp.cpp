// A small MLP (Linear layers, each optionally followed by ReLU) in bfloat16 on the CPU, forward and
// backward, with AVX512-BF16 dot products (vdpbf16ps) and float32 accumulation: issue 18's fused
// decoder.
//
// Registered as torch ops `torch.ops.scalar_nerf_mlp.forward`, `.backward` and `.supported`; the
// Python side (fields/fused_mlp.py) packs the weights, wraps the pair in an autograd function and
// uses it only where `supported()` says this CPU has AVX512-BF16. What the kernels must agree with
// is the same stack of layers in float32 with bfloat16-rounded inputs, weights and gradients
// (tests/test_fused_mlp.py).
//
// Why: autograd's layer-by-layer bfloat16 path (oneDNN products, then separate passes for the
// bias, ReLU, its backward, the bias gradient and bfloat16 <-> float32 copies) spent about 58 ms
// on a training step's decoder (90k samples) of which the products were about 32 ms. Here rows are
// taken 64 at a time through every layer while they are in the core's cache: the bias, ReLU and
// conversions are applied as results are written, and the backward's three products per layer
// (the input gradient, the weight gradient, the bias gradient) read each tile once.
//
// Layouts (all row-major; widths padded with zeros to multiples of 16, rows to multiples of 64):
//   activations[l]   bf16 [Npad, Kp_l]: layer l's input (the network's input for l = 0, else the
//                    previous layer's output after its ReLU), kept for the backward.
//   forward weights  bf16 [Kp_l / 2, Op_l, 2]: W[o, 2p], W[o, 2p + 1] side by side (vdpbf16ps takes
//                    pairs along the summed dimension).
//   backward weights bf16 [Op_l / 2, Kp_l, 2]: W[2p, k], W[2p + 1, k] side by side.
//   weight gradients float32 [Kp_l, Op_l] (the transpose of W's layout), bias gradients [Op_l].

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <omp.h>
#include <torch/library.h>

#include "check.h"
#include "mlp_common.h"

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define SCALAR_NERF_MLP_X86 1
#endif

namespace {

using scalar_nerf_mlp_common::kTile;
using scalar_nerf_mlp_common::Layer;
using scalar_nerf_mlp_common::PerThreadGradients;
using scalar_nerf_mlp_common::round_up;
using scalar_nerf_mlp_common::threads_for;

#ifdef SCALAR_NERF_MLP_X86
#define MLP_TARGET __attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16")))

// C[r, :] = init[:] + sum over pairs p of A32[r, p] . W32[p, :] for R rows and OB blocks of 16
// output columns starting at block ob0. A32: [rows, a_stride] int32 (bf16 pairs); W32: [kpairs,
// w_stride] int32 (bf16 pairs); C: float32 [rows, c_stride].
template <int OB, int R>
MLP_TARGET inline void gemm_block(const int32_t* a32, int64_t a_stride, const int32_t* w32, int64_t w_stride,
                                  int64_t kpairs, const float* init, int64_t ob0, float* c, int64_t c_stride) {
  __m512 acc[R][OB];
  for (int j = 0; j < OB; ++j) {
    const __m512 start = init != nullptr ? _mm512_loadu_ps(init + (ob0 + j) * 16) : _mm512_setzero_ps();
    for (int i = 0; i < R; ++i) acc[i][j] = start;
  }
  for (int64_t p = 0; p < kpairs; ++p) {
    __m512bh w[OB];
    for (int j = 0; j < OB; ++j) w[j] = (__m512bh)_mm512_loadu_si512(w32 + p * w_stride + (ob0 + j) * 16);
    for (int i = 0; i < R; ++i) {
      const __m512bh a = (__m512bh)_mm512_set1_epi32(a32[i * a_stride + p]);
      for (int j = 0; j < OB; ++j) acc[i][j] = _mm512_dpbf16_ps(acc[i][j], w[j], a);
    }
  }
  for (int i = 0; i < R; ++i)
    for (int j = 0; j < OB; ++j) _mm512_storeu_ps(c + i * c_stride + (ob0 + j) * 16, acc[i][j]);
}

template <int OB>
MLP_TARGET void gemm_rows_ob(const int32_t* a32, int64_t a_stride, const int32_t* w32, int64_t w_stride,
                             int64_t kpairs, const float* init, int64_t ob0, float* c, int64_t c_stride, int64_t rows) {
  constexpr int R = OB == 1 ? 8 : 4;
  for (int64_t r = 0; r < rows; r += R) {
    gemm_block<OB, R>(a32 + r * a_stride, a_stride, w32, w_stride, kpairs, init, ob0, c + r * c_stride, c_stride);
  }
}

// Calls f(std::integral_constant<int, OB>{}, ob0) for the output blocks of 16 columns taken up
// to 4 at a time (OB of them starting at block ob0): the kernels keep OB blocks in registers.
template <typename F>
void for_block_groups(int64_t out, F&& f) {
  const int64_t blocks = out / 16;
  for (int64_t ob0 = 0; ob0 < blocks; ob0 += 4) {
    switch (std::min<int64_t>(4, blocks - ob0)) {
      case 4: f(std::integral_constant<int, 4>{}, ob0); break;
      case 3: f(std::integral_constant<int, 3>{}, ob0); break;
      case 2: f(std::integral_constant<int, 2>{}, ob0); break;
      default: f(std::integral_constant<int, 1>{}, ob0); break;
    }
  }
}

// C [rows, out] (float32) = init + A [rows, 2 * kpairs] (bf16) x packed W; rows a multiple of 8.
MLP_TARGET void gemm_rows(const int32_t* a32, int64_t a_stride, const int32_t* w32, int64_t out, int64_t kpairs,
                          const float* init, float* c, int64_t rows) {
  for_block_groups(out, [&](auto ob, int64_t ob0) {
    gemm_rows_ob<decltype(ob)::value>(a32, a_stride, w32, out, kpairs, init, ob0, c, out, rows);
  });
}

MLP_TARGET inline void store_bf16(uint16_t* dst, __m512 v) {
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(dst), (__m256i)_mm512_cvtneps_pbh(v));
}

// Rows 2p and 2p + 1 of a bf16 [rows, width] matrix side by side: out32[p, c] = (row 2p)[c] | (row 2p+1)[c] << 16.
MLP_TARGET void interleave_rows(const uint16_t* src, int64_t width, int64_t rows, int32_t* out32) {
  for (int64_t p = 0; p < rows / 2; ++p) {
    const uint16_t* r0 = src + 2 * p * width;
    const uint16_t* r1 = r0 + width;
    for (int64_t c = 0; c < width; c += 16) {
      const __m512i lo = _mm512_cvtepu16_epi32(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(r0 + c)));
      const __m512i hi = _mm512_cvtepu16_epi32(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(r1 + c)));
      _mm512_storeu_si512(out32 + p * width + c, _mm512_or_si512(lo, _mm512_slli_epi32(hi, 16)));
    }
  }
}

// grad_wt [in, out] += sum over row pairs of Ai (pairs of input rows) x Zi (pairs of gradient rows).
template <int OB>
MLP_TARGET void weight_grad_ob(const int32_t* z32, const int32_t* a32, int64_t pairs, int64_t out, int64_t in,
                               int64_t ob0, float* grad_wt) {
  constexpr int KB = 4;
  for (int64_t k0 = 0; k0 < in; k0 += KB) {
    __m512 acc[KB][OB];
    for (int kk = 0; kk < KB; ++kk)
      for (int j = 0; j < OB; ++j) acc[kk][j] = _mm512_loadu_ps(grad_wt + (k0 + kk) * out + (ob0 + j) * 16);
    for (int64_t p = 0; p < pairs; ++p) {
      __m512bh z[OB];
      for (int j = 0; j < OB; ++j) z[j] = (__m512bh)_mm512_loadu_si512(z32 + p * out + (ob0 + j) * 16);
      for (int kk = 0; kk < KB; ++kk) {
        const __m512bh a = (__m512bh)_mm512_set1_epi32(a32[p * in + k0 + kk]);
        for (int j = 0; j < OB; ++j) acc[kk][j] = _mm512_dpbf16_ps(acc[kk][j], z[j], a);
      }
    }
    for (int kk = 0; kk < KB; ++kk)
      for (int j = 0; j < OB; ++j) _mm512_storeu_ps(grad_wt + (k0 + kk) * out + (ob0 + j) * 16, acc[kk][j]);
  }
}

MLP_TARGET void weight_grad(const int32_t* z32, const int32_t* a32, int64_t pairs, int64_t out, int64_t in,
                            float* grad_wt) {
  for_block_groups(out, [&](auto ob, int64_t ob0) {
    weight_grad_ob<decltype(ob)::value>(z32, a32, pairs, out, in, ob0, grad_wt);
  });
}

// One tile of the forward: activations[0] rows [r0, r0 + kTile) from the input, then every layer.
MLP_TARGET void forward_tile(const float* in_f32, const uint16_t* in_bf16, int64_t in_dim, const std::vector<Layer>& layers,
                             const std::vector<const int32_t*>& weights, const std::vector<const float*>& biases,
                             const std::vector<uint16_t*>& acts, float* out, int64_t out_dim, int64_t n, int64_t r0,
                             float* scratch) {
  const int64_t kp0 = layers[0].in_padded;
  uint16_t* a0 = acts[0] + r0 * kp0;
  for (int64_t r = 0; r < kTile; ++r) {
    uint16_t* dst = a0 + r * kp0;
    if (r0 + r >= n) {
      std::memset(dst, 0, kp0 * sizeof(uint16_t));
      continue;
    }
    for (int64_t c = 0; c < kp0; c += 16) {
      const int64_t left = std::min<int64_t>(16, in_dim - c);
      if (left <= 0) {
        std::memset(dst + c, 0, 16 * sizeof(uint16_t));
        continue;
      }
      const __mmask16 mask = static_cast<__mmask16>((1u << left) - 1u);
      if (in_f32 != nullptr) {
        store_bf16(dst + c, _mm512_maskz_loadu_ps(mask, in_f32 + (r0 + r) * in_dim + c));
      } else {
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(dst + c),
                            _mm256_maskz_loadu_epi16(mask, in_bf16 + (r0 + r) * in_dim + c));
      }
    }
  }
  const int64_t num_layers = static_cast<int64_t>(layers.size());
  for (int64_t l = 0; l < num_layers; ++l) {
    const Layer& ly = layers[l];
    const int32_t* a32 = reinterpret_cast<const int32_t*>(acts[l] + r0 * ly.in_padded);
    gemm_rows(a32, ly.in_padded / 2, weights[l], ly.out_padded, ly.in_padded / 2, biases[l], scratch, kTile);
    if (l + 1 < num_layers) {
      uint16_t* next = acts[l + 1] + r0 * ly.out_padded;
      const __m512 zero = _mm512_setzero_ps();
      for (int64_t r = 0; r < kTile; ++r)
        for (int64_t c = 0; c < ly.out_padded; c += 16) {
          __m512 v = _mm512_loadu_ps(scratch + r * ly.out_padded + c);
          if (ly.relu) v = _mm512_max_ps(zero, v);  // a NaN stays NaN (vmaxps returns its second operand then)
          store_bf16(next + r * ly.out_padded + c, v);
        }
    } else {
      for (int64_t r = 0; r < kTile && r0 + r < n; ++r)
        std::memcpy(out + (r0 + r) * out_dim, scratch + r * ly.out_padded, out_dim * sizeof(float));
    }
  }
}

struct BackwardScratch {
  std::vector<float> dz;       // [kTile, max width] float32 gradient of the current layer's pre-activation
  std::vector<float> da;       // [kTile, max width] float32 gradient of its input
  std::vector<uint16_t> dz16;  // [kTile, max width] bf16 copy of dz
  std::vector<int32_t> dz32;   // [kTile / 2, max width] dz16's row pairs
  std::vector<int32_t> a32;    // [kTile / 2, max width] the layer input's row pairs
};

MLP_TARGET void backward_tile(const float* grad_out, int64_t out_dim, const std::vector<Layer>& layers,
                              const std::vector<const int32_t*>& weights_t, const std::vector<const uint16_t*>& acts,
                              float* grad_in, int64_t in_dim, int64_t n, int64_t r0,
                              const std::vector<float*>& grad_wt, const std::vector<float*>& grad_b,
                              BackwardScratch& s) {
  const int64_t num_layers = static_cast<int64_t>(layers.size());
  const int64_t last_out = layers.back().out_padded;
  for (int64_t r = 0; r < kTile; ++r) {
    float* dst = s.dz.data() + r * last_out;
    std::fill(dst, dst + last_out, 0.0f);
    if (r0 + r < n) std::memcpy(dst, grad_out + (r0 + r) * out_dim, out_dim * sizeof(float));
  }
  for (int64_t l = num_layers - 1; l >= 0; --l) {
    const Layer& ly = layers[l];
    const int64_t op = ly.out_padded, kp = ly.in_padded;
    // bias gradient (float32) and the bf16 copy of dz
    for (int64_t c = 0; c < op; c += 16) {
      __m512 sum = _mm512_loadu_ps(grad_b[l] + c);
      for (int64_t r = 0; r < kTile; ++r) {
        const __m512 v = _mm512_loadu_ps(s.dz.data() + r * op + c);
        sum = _mm512_add_ps(sum, v);
        store_bf16(s.dz16.data() + r * op + c, v);
      }
      _mm512_storeu_ps(grad_b[l] + c, sum);
    }
    // weight gradient
    const uint16_t* a = acts[l] + r0 * kp;
    interleave_rows(s.dz16.data(), op, kTile, s.dz32.data());
    interleave_rows(a, kp, kTile, s.a32.data());
    weight_grad(s.dz32.data(), s.a32.data(), kTile / 2, op, kp, grad_wt[l]);
    if (l == 0 && grad_in == nullptr) break;
    // input gradient: da = dz W
    gemm_rows(reinterpret_cast<const int32_t*>(s.dz16.data()), op / 2, weights_t[l], kp, op / 2, nullptr,
              s.da.data(), kTile);
    if (l == 0) {
      for (int64_t r = 0; r < kTile && r0 + r < n; ++r)
        std::memcpy(grad_in + (r0 + r) * in_dim, s.da.data() + r * kp, in_dim * sizeof(float));
      break;
    }
    // through the previous layer's ReLU: its output is this layer's input `a`
    const bool relu = layers[l - 1].relu;
    for (int64_t r = 0; r < kTile; ++r)
      for (int64_t c = 0; c < kp; c += 16) {
        __m512 v = _mm512_loadu_ps(s.da.data() + r * kp + c);
        if (relu) {
          const __m256i bits = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(a + r * kp + c));
          v = _mm512_maskz_mov_ps(_mm256_cmpgt_epi16_mask(bits, _mm256_setzero_si256()), v);
        }
        _mm512_storeu_ps(s.dz.data() + r * kp + c, v);
      }
  }
}
#endif  // SCALAR_NERF_MLP_X86

bool supported() {
#ifdef SCALAR_NERF_MLP_X86
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx512bf16") && __builtin_cpu_supports("avx512bw") &&
         __builtin_cpu_supports("avx512vl");
#else
  return false;
#endif
}

void check(bool ok, const char* what) { SCALAR_CHECK(ok, "scalar_nerf_mlp: ", what); }

std::vector<Layer> check_layers(const std::vector<at::Tensor>& weights, const std::vector<int64_t>& relu, bool transposed) {
  check(!weights.empty(), "need at least one layer");
  check(weights.size() == relu.size(), "one relu flag per layer");
  check(relu.back() == 0, "the last layer cannot have a ReLU");
  std::vector<Layer> layers;
  for (size_t l = 0; l < weights.size(); ++l) {
    const at::Tensor& w = weights[l];
    SCALAR_CHECK(w.device().is_cpu() && w.scalar_type() == at::kBFloat16 && w.is_contiguous() && w.dim() == 3 &&
                     w.size(2) == 2,
                 "scalar_nerf_mlp: packed weight ", l, " must be a contiguous CPU bfloat16 [P, W, 2] tensor, got ",
                 w.sizes(), " ", w.scalar_type());
    Layer ly;
    ly.in_padded = transposed ? w.size(1) : 2 * w.size(0);
    ly.out_padded = transposed ? 2 * w.size(0) : w.size(1);
    ly.relu = relu[l] != 0;
    SCALAR_CHECK(ly.in_padded % 16 == 0 && ly.out_padded % 16 == 0 && ly.in_padded > 0 && ly.out_padded > 0,
                 "scalar_nerf_mlp: padded widths must be positive multiples of 16, layer ", l, " has ", ly.in_padded,
                 " -> ", ly.out_padded);
    if (l > 0)
      SCALAR_CHECK(ly.in_padded == layers.back().out_padded, "scalar_nerf_mlp: layer ", l, " takes ", ly.in_padded,
                   " inputs but layer ", l - 1, " gives ", layers.back().out_padded);
    layers.push_back(ly);
  }
  return layers;
}

// input [N, K0] float32 or bf16 -> [output float32 [N, out_dim], activations[0..L-1] bf16 [Npad, Kp_l]].
std::vector<at::Tensor> forward(const at::Tensor& input, const std::vector<at::Tensor>& weights,
                                const std::vector<at::Tensor>& biases, const std::vector<int64_t>& relu, int64_t out_dim) {
  check(supported(), "this CPU has no AVX512-BF16");
  const std::vector<Layer> layers = check_layers(weights, relu, false);
  SCALAR_CHECK(input.device().is_cpu() && input.is_contiguous() && input.dim() == 2 &&
                   (input.scalar_type() == at::kFloat || input.scalar_type() == at::kBFloat16),
               "scalar_nerf_mlp: input must be a contiguous CPU float32 or bfloat16 [N, K] tensor");
  SCALAR_CHECK(input.size(1) <= layers[0].in_padded, "scalar_nerf_mlp: input has ", input.size(1),
               " columns, the first layer takes ", layers[0].in_padded);
  SCALAR_CHECK(out_dim >= 1 && out_dim <= layers.back().out_padded, "scalar_nerf_mlp: out_dim ", out_dim,
               " out of range");
  check(biases.size() == layers.size(), "one bias per layer");
  std::vector<const int32_t*> w32;
  std::vector<const float*> b32;
  for (size_t l = 0; l < layers.size(); ++l) {
    SCALAR_CHECK(biases[l].scalar_type() == at::kFloat && biases[l].is_contiguous() &&
                     biases[l].numel() == layers[l].out_padded,
                 "scalar_nerf_mlp: bias ", l, " must be contiguous float32 with ", layers[l].out_padded, " values");
    w32.push_back(reinterpret_cast<const int32_t*>(weights[l].data_ptr<at::BFloat16>()));
    b32.push_back(biases[l].data_ptr<float>());
  }
  const int64_t n = input.size(0);
  const int64_t npad = round_up(std::max<int64_t>(n, 1), kTile);
  const auto bf16 = input.options().dtype(at::kBFloat16);
  std::vector<at::Tensor> result;
  result.push_back(at::empty({n, out_dim}, input.options().dtype(at::kFloat)));
  std::vector<uint16_t*> acts;
  for (const Layer& ly : layers) {
    result.push_back(at::empty({npad, ly.in_padded}, bf16));
    acts.push_back(reinterpret_cast<uint16_t*>(result.back().data_ptr<at::BFloat16>()));
  }
#ifdef SCALAR_NERF_MLP_X86
  int64_t widest = 0;
  for (const Layer& ly : layers) widest = std::max(widest, ly.out_padded);
  float* out = result[0].data_ptr<float>();
  const bool is_f32 = input.scalar_type() == at::kFloat;
  const float* in_f32 = is_f32 ? input.data_ptr<float>() : nullptr;
  const uint16_t* in_bf16 = is_f32 ? nullptr : reinterpret_cast<const uint16_t*>(input.data_ptr<at::BFloat16>());
  const int64_t tiles = npad / kTile;
#pragma omp parallel num_threads(threads_for(tiles))
  {
    std::vector<float> scratch(kTile * widest);
#pragma omp for schedule(static)
    for (int64_t t = 0; t < tiles; ++t)
      forward_tile(in_f32, in_bf16, input.size(1), layers, w32, b32, acts, out, out_dim, n, t * kTile,
                   scratch.data());
  }
#endif
  return result;
}

// grad_out [N, out_dim] float32, the forward's activations, weights packed for the backward ->
// [grad_input float32 [N, in_dim] (empty when in_dim == 0), then per layer grad_wt float32 [Kp, Op], grad_b [Op]].
std::vector<at::Tensor> backward(const at::Tensor& grad_out, const std::vector<at::Tensor>& activations,
                                 const std::vector<at::Tensor>& weights_t, const std::vector<int64_t>& relu,
                                 int64_t in_dim) {
  check(supported(), "this CPU has no AVX512-BF16");
  const std::vector<Layer> layers = check_layers(weights_t, relu, true);
  SCALAR_CHECK(grad_out.device().is_cpu() && grad_out.scalar_type() == at::kFloat && grad_out.is_contiguous() &&
                   grad_out.dim() == 2 && grad_out.size(1) <= layers.back().out_padded,
               "scalar_nerf_mlp: grad_out must be a contiguous CPU float32 [N, out] tensor, got ", grad_out.sizes());
  check(activations.size() == layers.size(), "one activation per layer");
  const int64_t n = grad_out.size(0);
  const int64_t npad = round_up(std::max<int64_t>(n, 1), kTile);
  std::vector<const uint16_t*> acts;
  for (size_t l = 0; l < layers.size(); ++l) {
    const at::Tensor& a = activations[l];
    SCALAR_CHECK(a.scalar_type() == at::kBFloat16 && a.is_contiguous() && a.dim() == 2 && a.size(0) == npad &&
                     a.size(1) == layers[l].in_padded,
                 "scalar_nerf_mlp: activation ", l, " must be bfloat16 [", npad, ", ", layers[l].in_padded, "], got ",
                 a.sizes());
    acts.push_back(reinterpret_cast<const uint16_t*>(a.data_ptr<at::BFloat16>()));
  }
  SCALAR_CHECK(in_dim >= 0 && in_dim <= layers[0].in_padded, "scalar_nerf_mlp: in_dim ", in_dim, " out of range");
  std::vector<const int32_t*> w32;
  for (const at::Tensor& w : weights_t) w32.push_back(reinterpret_cast<const int32_t*>(w.data_ptr<at::BFloat16>()));
  const int64_t tiles = npad / kTile;
  const int threads = threads_for(tiles);
  const auto f32 = grad_out.options();
  at::Tensor grad_in = at::empty({in_dim > 0 ? n : 0, in_dim}, f32);
  const PerThreadGradients grads(layers, threads, f32);
#ifdef SCALAR_NERF_MLP_X86
  int64_t widest = 0;
  for (const Layer& ly : layers) widest = std::max({widest, ly.in_padded, ly.out_padded});
  float* gin = in_dim > 0 ? grad_in.data_ptr<float>() : nullptr;
  const float* gout = grad_out.data_ptr<float>();
  const int64_t out_dim = grad_out.size(1);
#pragma omp parallel num_threads(threads)
  {
    const int t = omp_get_thread_num();
    BackwardScratch s;
    s.dz.resize(kTile * widest);
    s.da.resize(kTile * widest);
    s.dz16.resize(kTile * widest);
    s.dz32.resize(kTile / 2 * widest);
    s.a32.resize(kTile / 2 * widest);
    std::vector<float*> gwt, gb;
    grads.slices(t, gwt, gb);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < tiles; ++i)
      backward_tile(gout, out_dim, layers, w32, acts, gin, in_dim, n, i * kTile, gwt, gb, s);
  }
#endif
  return grads.result(grad_in);
}

}  // namespace

TORCH_LIBRARY(scalar_nerf_mlp, m) {
  m.def("supported() -> bool", &supported);
  m.def("forward(Tensor input, Tensor[] weights, Tensor[] biases, int[] relu, int out_dim) -> Tensor[]", &forward);
  m.def("backward(Tensor grad_out, Tensor[] activations, Tensor[] weights_t, int[] relu, int in_dim) -> Tensor[]",
        &backward);
}
