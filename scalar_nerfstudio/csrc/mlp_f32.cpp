// A small MLP (Linear layers, each optionally followed by ReLU) in float32 on the CPU, forward and
// backward in one pass over 64-row tiles each: issue 67's fused decoder for CPUs without
// AVX512-BF16 (the bfloat16 one is csrc/mlp.cpp).
//
// Registered as torch ops `torch.ops.scalar_nerf_mlp_f32.forward`, `.backward`, `.infer` (no autograd:
// the activations stay in per-thread tile buffers) and `.isa`; the
// Python side is fields/fused_mlp_float32.py. The per-tile kernels (csrc/mlp_f32_kernels.h) are
// compiled twice: with AVX2 + FMA (per-function target, chosen at run time where the CPU has both)
// and with the compiler's baseline target (the "portable" fallback, also the only one off x86). The
// extension is built without -march, so the binary runs on any CPU of its architecture.
//
// What the kernels must agree with is torch's float32 layers (tests/test_fused_mlp_float32.py); sums
// run in another order (and with fused multiply-adds), so results differ in the last bits.
//
// Layouts (row-major float32; widths padded with zeros to multiples of 8, rows to multiples of 64):
//   activations[l]   [Npad, Kp_l]: layer l's input (the network's input for l = 0, else the
//                    previous layer's output after its ReLU), kept for the backward.
//   forward weights  [Kp_l, Op_l]: W transposed.      backward weights [Op_l, Kp_l]: W.
//   biases           [Op_l].      weight gradients   [Kp_l, Op_l] (W's transpose), bias gradients [Op_l].

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
#include <string>
#include <utility>
#include <vector>

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define SCALAR_NERF_MLP_F32_X86 1
#endif

namespace {

using scalar_nerf_mlp_common::kTile;  // a multiple of every row block of the kernels (4, 8)
using scalar_nerf_mlp_common::Layer;
using scalar_nerf_mlp_common::PerThreadGradients;
using scalar_nerf_mlp_common::round_up;
using scalar_nerf_mlp_common::threads_for;

constexpr int64_t kWidthMultiple = 8;

struct TileScratch {
  std::vector<float> dz;  // [kTile, widest] gradient of the current layer's pre-activation
  std::vector<float> da;  // [kTile, widest] gradient of its input
};

typedef float V8 __attribute__((vector_size(32)));
typedef float V8u __attribute__((vector_size(32), aligned(4), may_alias));  // for unaligned loads and stores

namespace portable {
#include "mlp_f32_kernels.h"
}  // namespace portable

#ifdef SCALAR_NERF_MLP_F32_X86
#if defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx2,fma"))), apply_to = function)
#else
#pragma GCC push_options
#pragma GCC target("avx2,fma")
#endif
namespace avx2 {
#include "mlp_f32_kernels.h"
}  // namespace avx2
#if defined(__clang__)
#pragma clang attribute pop
#else
#pragma GCC pop_options
#endif
#endif  // SCALAR_NERF_MLP_F32_X86

bool cpu_has_avx2() {
#ifdef SCALAR_NERF_MLP_F32_X86
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
#else
  return false;
#endif
}

// The best kernels this CPU runs: "avx2" or "portable".
std::string isa() { return cpu_has_avx2() ? "avx2" : "portable"; }

struct Kernels {
  decltype(&portable::forward_tile) forward_tile;
  decltype(&portable::backward_tile) backward_tile;
  decltype(&portable::infer_tile) infer_tile;
};

Kernels kernels_for(const std::string& name) {
  if (name == "portable") return {&portable::forward_tile, &portable::backward_tile, &portable::infer_tile};
#ifdef SCALAR_NERF_MLP_F32_X86
  if (name == "avx2") {
    SCALAR_CHECK(cpu_has_avx2(), "scalar_nerf_mlp_f32: isa 'avx2' asked for, but this CPU lacks AVX2 or FMA");
    return {&avx2::forward_tile, &avx2::backward_tile, &avx2::infer_tile};
  }
#endif
  SCALAR_CHECK(false, "scalar_nerf_mlp_f32: isa must be 'avx2' (x86 only) or 'portable', got '", name, "'");
  return {nullptr, nullptr, nullptr};
}

// Layers from the packed weights: [Kp, Op] (transposed == false, forward) or [Op, Kp] (backward).
std::vector<Layer> check_layers(const std::vector<at::Tensor>& weights, const std::vector<int64_t>& relu, bool backward) {
  SCALAR_CHECK(!weights.empty(), "scalar_nerf_mlp_f32: need at least one layer");
  SCALAR_CHECK(weights.size() == relu.size(), "scalar_nerf_mlp_f32: one relu flag per layer");
  SCALAR_CHECK(relu.back() == 0, "scalar_nerf_mlp_f32: the last layer cannot have a ReLU");
  std::vector<Layer> layers;
  for (size_t l = 0; l < weights.size(); ++l) {
    const at::Tensor& w = weights[l];
    SCALAR_CHECK(w.device().is_cpu() && w.scalar_type() == at::kFloat && w.is_contiguous() && w.dim() == 2,
                 "scalar_nerf_mlp_f32: packed weight ", l, " must be a contiguous CPU float32 2-d tensor, got ",
                 w.sizes(), " ", w.scalar_type());
    Layer ly;
    ly.in_padded = backward ? w.size(1) : w.size(0);
    ly.out_padded = backward ? w.size(0) : w.size(1);
    ly.relu = relu[l] != 0;
    SCALAR_CHECK(ly.in_padded % kWidthMultiple == 0 && ly.out_padded % kWidthMultiple == 0 && ly.in_padded > 0 &&
                     ly.out_padded > 0,
                 "scalar_nerf_mlp_f32: padded widths must be positive multiples of 8, layer ", l, " has ",
                 ly.in_padded, " -> ", ly.out_padded);
    if (l > 0)
      SCALAR_CHECK(ly.in_padded == layers.back().out_padded, "scalar_nerf_mlp_f32: layer ", l, " takes ",
                   ly.in_padded, " inputs but layer ", l - 1, " gives ", layers.back().out_padded);
    layers.push_back(ly);
  }
  return layers;
}

// The forward's layers, weight and bias pointers, after checking the input and the packed parameters.
struct ForwardArguments {
  std::vector<Layer> layers;
  std::vector<const float*> w32, b32;
};

ForwardArguments check_forward(const at::Tensor& input, const std::vector<at::Tensor>& weights_t,
                               const std::vector<at::Tensor>& biases, const std::vector<int64_t>& relu, int64_t out_dim) {
  ForwardArguments args{check_layers(weights_t, relu, false), {}, {}};
  const std::vector<Layer>& layers = args.layers;
  SCALAR_CHECK(input.device().is_cpu() && input.is_contiguous() && input.dim() == 2 &&
                   input.scalar_type() == at::kFloat,
               "scalar_nerf_mlp_f32: input must be a contiguous CPU float32 [N, K] tensor, got ", input.sizes(), " ",
               input.scalar_type());
  SCALAR_CHECK(input.size(1) <= layers[0].in_padded, "scalar_nerf_mlp_f32: input has ", input.size(1),
               " columns, the first layer takes ", layers[0].in_padded);
  SCALAR_CHECK(out_dim >= 1 && out_dim <= layers.back().out_padded, "scalar_nerf_mlp_f32: out_dim ", out_dim,
               " out of range");
  SCALAR_CHECK(biases.size() == layers.size(), "scalar_nerf_mlp_f32: one bias per layer");
  for (size_t l = 0; l < layers.size(); ++l) {
    SCALAR_CHECK(biases[l].scalar_type() == at::kFloat && biases[l].is_contiguous() &&
                     biases[l].numel() == layers[l].out_padded,
                 "scalar_nerf_mlp_f32: bias ", l, " must be contiguous float32 with ", layers[l].out_padded, " values");
    args.w32.push_back(weights_t[l].data_ptr<float>());
    args.b32.push_back(biases[l].data_ptr<float>());
  }
  return args;
}

// input [N, K0] float32 -> [output [N, out_dim], activations[0..L-1] [Npad, Kp_l]].
std::vector<at::Tensor> forward(const at::Tensor& input, const std::vector<at::Tensor>& weights_t,
                                const std::vector<at::Tensor>& biases, const std::vector<int64_t>& relu, int64_t out_dim,
                                const std::string& isa_name) {
  const Kernels kernels = kernels_for(isa_name);
  const ForwardArguments args = check_forward(input, weights_t, biases, relu, out_dim);
  const std::vector<Layer>& layers = args.layers;
  const std::vector<const float*>& w32 = args.w32;
  const std::vector<const float*>& b32 = args.b32;
  const int64_t n = input.size(0);
  const int64_t npad = round_up(std::max<int64_t>(n, 1), kTile);
  std::vector<at::Tensor> result;
  result.push_back(at::empty({n, out_dim}, input.options()));
  std::vector<float*> acts;
  for (const Layer& ly : layers) {
    result.push_back(at::empty({npad, ly.in_padded}, input.options()));
    acts.push_back(result.back().data_ptr<float>());
  }
  float* out = result[0].data_ptr<float>();
  const float* in = input.data_ptr<float>();
  const int64_t in_dim = input.size(1);
  const int64_t last = layers.back().out_padded;
  const int64_t tiles = npad / kTile;
#pragma omp parallel num_threads(threads_for(tiles))
  {
    std::vector<float> scratch(kTile * last);
#pragma omp for schedule(static)
    for (int64_t t = 0; t < tiles; ++t)
      kernels.forward_tile(in, in_dim, layers, w32, b32, acts, out, out_dim, n, t * kTile, scratch.data());
  }
  return result;
}

// input [N, K0] float32 -> output [N, out_dim], without autograd: no activation is kept.
at::Tensor infer(const at::Tensor& input, const std::vector<at::Tensor>& weights_t, const std::vector<at::Tensor>& biases,
                 const std::vector<int64_t>& relu, int64_t out_dim, const std::string& isa_name) {
  const Kernels kernels = kernels_for(isa_name);
  const ForwardArguments args = check_forward(input, weights_t, biases, relu, out_dim);
  const std::vector<Layer>& layers = args.layers;
  const int64_t n = input.size(0);
  at::Tensor output = at::empty({n, out_dim}, input.options());
  if (n == 0) return output;
  const int64_t tiles = round_up(n, kTile) / kTile;
  float* out = output.data_ptr<float>();
  const float* in = input.data_ptr<float>();
  const int64_t in_dim = input.size(1);
#pragma omp parallel num_threads(threads_for(tiles))
  {
    std::vector<std::vector<float>> storage;
    std::vector<float*> bufs;
    for (const Layer& ly : layers) storage.emplace_back(kTile * ly.in_padded);
    storage.emplace_back(kTile * layers.back().out_padded);
    for (std::vector<float>& buf : storage) bufs.push_back(buf.data());
#pragma omp for schedule(static)
    for (int64_t t = 0; t < tiles; ++t)
      kernels.infer_tile(in, in_dim, layers, args.w32, args.b32, bufs, out, out_dim, n, t * kTile);
  }
  return output;
}

// grad_out [N, out_dim], the forward's activations, weights packed for the backward ->
// [grad_input [N, in_dim] (empty when in_dim == 0), then per layer grad_wt [Kp, Op], grad_b [Op]].
std::vector<at::Tensor> backward(const at::Tensor& grad_out, const std::vector<at::Tensor>& activations,
                                 const std::vector<at::Tensor>& weights, const std::vector<int64_t>& relu,
                                 int64_t in_dim, const std::string& isa_name) {
  const Kernels kernels = kernels_for(isa_name);
  const std::vector<Layer> layers = check_layers(weights, relu, true);
  SCALAR_CHECK(grad_out.device().is_cpu() && grad_out.scalar_type() == at::kFloat && grad_out.is_contiguous() &&
                   grad_out.dim() == 2 && grad_out.size(1) <= layers.back().out_padded,
               "scalar_nerf_mlp_f32: grad_out must be a contiguous CPU float32 [N, out] tensor, got ",
               grad_out.sizes());
  SCALAR_CHECK(activations.size() == layers.size(), "scalar_nerf_mlp_f32: one activation per layer");
  const int64_t n = grad_out.size(0);
  const int64_t npad = round_up(std::max<int64_t>(n, 1), kTile);
  std::vector<const float*> acts;
  for (size_t l = 0; l < layers.size(); ++l) {
    const at::Tensor& a = activations[l];
    SCALAR_CHECK(a.scalar_type() == at::kFloat && a.is_contiguous() && a.dim() == 2 && a.size(0) == npad &&
                     a.size(1) == layers[l].in_padded,
                 "scalar_nerf_mlp_f32: activation ", l, " must be float32 [", npad, ", ", layers[l].in_padded,
                 "], got ", a.sizes());
    acts.push_back(a.data_ptr<float>());
  }
  SCALAR_CHECK(in_dim >= 0 && in_dim <= layers[0].in_padded, "scalar_nerf_mlp_f32: in_dim ", in_dim, " out of range");
  std::vector<const float*> w32;
  for (const at::Tensor& w : weights) w32.push_back(w.data_ptr<float>());
  const int64_t tiles = npad / kTile;
  const int threads = threads_for(tiles);
  const auto f32 = grad_out.options();
  at::Tensor grad_in = at::empty({in_dim > 0 ? n : 0, in_dim}, f32);
  const PerThreadGradients grads(layers, threads, f32);
  int64_t widest = 0;
  for (const Layer& ly : layers) widest = std::max({widest, ly.in_padded, ly.out_padded});
  float* gin = in_dim > 0 ? grad_in.data_ptr<float>() : nullptr;
  const float* gout = grad_out.data_ptr<float>();
  const int64_t out_dim = grad_out.size(1);
#pragma omp parallel num_threads(threads)
  {
    const int t = omp_get_thread_num();
    TileScratch s;
    s.dz.resize(kTile * widest);
    s.da.resize(kTile * widest);
    std::vector<float*> gwt, gb;
    grads.slices(t, gwt, gb);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < tiles; ++i)
      kernels.backward_tile(gout, out_dim, layers, w32, acts, gin, in_dim, n, i * kTile, gwt, gb, s);
  }
  return grads.result(grad_in);
}

}  // namespace

TORCH_LIBRARY(scalar_nerf_mlp_f32, m) {
  m.def("isa() -> str", &isa);
  m.def("forward(Tensor input, Tensor[] weights_t, Tensor[] biases, int[] relu, int out_dim, str isa) -> Tensor[]",
        &forward);
  m.def("infer(Tensor input, Tensor[] weights_t, Tensor[] biases, int[] relu, int out_dim, str isa) -> Tensor", &infer);
  m.def("backward(Tensor grad_out, Tensor[] activations, Tensor[] weights, int[] relu, int in_dim, str isa) -> Tensor[]",
        &backward);
}
