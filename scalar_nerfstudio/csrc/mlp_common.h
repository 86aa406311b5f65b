// What the two fused MLP ops share (csrc/mlp.cpp: bfloat16, AVX512-BF16; csrc/mlp_f32.cpp: float32):
// the tile of rows, a layer's padded shape, the thread count for a number of tiles, and the
// per-thread weight and bias gradients a backward writes and sums at its end.
#pragma once

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <cstdint>
#include <vector>

namespace scalar_nerf_mlp_common {

constexpr int64_t kTile = 64;  // rows per tile: even, and a multiple of every row block of the kernels

struct Layer {
  int64_t in_padded;   // Kp
  int64_t out_padded;  // Op
  bool relu;
};

inline int64_t round_up(int64_t v, int64_t m) { return (v + m - 1) / m * m; }

// Threads for `tiles` tiles: torch's thread count, at most one per tile, at least one.
inline int threads_for(int64_t tiles) {
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), tiles)));
}

// Each thread's float32 gradients of every layer's weights [threads, Kp, Op] (W's transpose) and
// biases [threads, Op], zeroed; summed over the threads by `result`.
class PerThreadGradients {
 public:
  PerThreadGradients(const std::vector<Layer>& layers, int threads, const at::TensorOptions& f32) : threads_(threads) {
    for (const Layer& ly : layers) {
      weight_.push_back(at::zeros({threads, ly.in_padded, ly.out_padded}, f32));
      bias_.push_back(at::zeros({threads, ly.out_padded}, f32));
    }
  }

  // Thread t's slices, one pointer per layer.
  void slices(int t, std::vector<float*>& weight, std::vector<float*>& bias) const {
    for (size_t l = 0; l < weight_.size(); ++l) {
      weight.push_back(weight_[l].data_ptr<float>() + t * weight_[l].size(1) * weight_[l].size(2));
      bias.push_back(bias_[l].data_ptr<float>() + t * bias_[l].size(1));
    }
  }

  // [grad_in, then per layer the weight gradient [Kp, Op] and the bias gradient [Op]].
  std::vector<at::Tensor> result(const at::Tensor& grad_in) const {
    std::vector<at::Tensor> out{grad_in};
    for (size_t l = 0; l < weight_.size(); ++l) {
      out.push_back(threads_ == 1 ? weight_[l][0] : weight_[l].sum(0));
      out.push_back(threads_ == 1 ? bias_[l][0] : bias_[l].sum(0));
    }
    return out;
  }

 private:
  int threads_;
  std::vector<at::Tensor> weight_, bias_;
};

}  // namespace scalar_nerf_mlp_common
