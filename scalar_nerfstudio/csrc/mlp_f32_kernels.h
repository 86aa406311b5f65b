// The float32 fused MLP's per-tile kernels (csrc/mlp_f32.cpp). No include guard: mlp_f32.cpp
// includes this file twice, once inside `namespace avx2` under an AVX2+FMA target pragma and once
// inside `namespace portable` with the compiler's baseline target, so that one source gives both
// the AVX2 kernels and the plain C++ fallback. The code uses GCC/Clang vector extensions (V8: 8
// floats), which the compiler maps to one ymm register with AVX2, to two xmm registers with SSE2
// and to two NEON registers on aarch64; `acc + a * w` becomes a fused multiply-add where the target
// has one (floating-point contraction).
//
// Types (Layer, TileScratch, kTile) come from the including file.

inline V8 load8(const float* p) { return *reinterpret_cast<const V8u*>(p); }
inline void store8(float* p, V8 v) { *reinterpret_cast<V8u*>(p) = v; }
inline V8 splat8(float x) { return V8{x, x, x, x, x, x, x, x}; }

// C[r, ob0*8 : (ob0+OB)*8] = init + sum_k A[r, k] * B[k, :] for R rows, optionally followed by a
// ReLU. A: [R, a_stride] rows; B: [K, b_stride]; C: [R, c_stride].
template <int OB, int R>
inline void gemm_block(const float* a, int64_t a_stride, const float* b, int64_t b_stride, int64_t k_count,
                       const float* init, int64_t ob0, bool relu, float* c, int64_t c_stride) {
  V8 acc[R][OB];
  for (int j = 0; j < OB; ++j) {
    const V8 start = init != nullptr ? load8(init + (ob0 + j) * 8) : V8{};
    for (int i = 0; i < R; ++i) acc[i][j] = start;
  }
  for (int64_t k = 0; k < k_count; ++k) {
    V8 w[OB];
    for (int j = 0; j < OB; ++j) w[j] = load8(b + k * b_stride + (ob0 + j) * 8);
    for (int i = 0; i < R; ++i) {
      const V8 x = splat8(a[i * a_stride + k]);
      for (int j = 0; j < OB; ++j) acc[i][j] += x * w[j];
    }
  }
  const V8 zero{};
  for (int i = 0; i < R; ++i)
    for (int j = 0; j < OB; ++j) {
      V8 v = acc[i][j];
      if (relu) v = v < zero ? zero : v;  // a NaN stays NaN, as in torch.relu
      store8(c + i * c_stride + (ob0 + j) * 8, v);
    }
}

// Rows [0, kTile) of C [kTile, out] = init + A [kTile, k_count] B [k_count, out] (+ ReLU): output
// columns in groups of up to 3 blocks of 8 (12 accumulators of 8 floats: the 16 ymm registers hold
// them, the group's 3 weight vectors and one broadcast input).
inline void gemm_tile(const float* a, int64_t a_stride, const float* b, int64_t out, int64_t k_count, const float* init,
                      bool relu, float* c, int64_t c_stride) {
  const int64_t blocks = out / 8;
  for (int64_t ob0 = 0; ob0 < blocks; ob0 += 3) {
    const int64_t group = std::min<int64_t>(3, blocks - ob0);
    for (int64_t r = 0; r < kTile; r += (group == 1 ? 8 : 4)) {
      const float* ar = a + r * a_stride;
      float* cr = c + r * c_stride;
      if (group == 3) {
        gemm_block<3, 4>(ar, a_stride, b, out, k_count, init, ob0, relu, cr, c_stride);
      } else if (group == 2) {
        gemm_block<2, 4>(ar, a_stride, b, out, k_count, init, ob0, relu, cr, c_stride);
      } else {
        gemm_block<1, 8>(ar, a_stride, b, out, k_count, init, ob0, relu, cr, c_stride);
      }
    }
  }
}

// grad_wt [in, out] += A^T Z over the kTile rows of a tile: A [kTile, in] (the layer's input),
// Z [kTile, out] (the gradient of its pre-activation). 4 input columns x up to 3 output blocks
// of accumulators at a time.
template <int OB>
inline void weight_grad_block(const float* z, const float* a, int64_t out, int64_t in, int64_t k0, int64_t ob0,
                              float* grad_wt) {
  constexpr int KB = 4;
  V8 acc[KB][OB];
  for (int kk = 0; kk < KB; ++kk)
    for (int j = 0; j < OB; ++j) acc[kk][j] = load8(grad_wt + (k0 + kk) * out + (ob0 + j) * 8);
  for (int64_t r = 0; r < kTile; ++r) {
    V8 zv[OB];
    for (int j = 0; j < OB; ++j) zv[j] = load8(z + r * out + (ob0 + j) * 8);
    for (int kk = 0; kk < KB; ++kk) {
      const V8 x = splat8(a[r * in + k0 + kk]);
      for (int j = 0; j < OB; ++j) acc[kk][j] += x * zv[j];
    }
  }
  for (int kk = 0; kk < KB; ++kk)
    for (int j = 0; j < OB; ++j) store8(grad_wt + (k0 + kk) * out + (ob0 + j) * 8, acc[kk][j]);
}

inline void weight_grad(const float* z, const float* a, int64_t out, int64_t in, float* grad_wt) {
  const int64_t blocks = out / 8;
  for (int64_t ob0 = 0; ob0 < blocks; ob0 += 3) {
    const int64_t group = std::min<int64_t>(3, blocks - ob0);
    for (int64_t k0 = 0; k0 < in; k0 += 4) {
      if (group == 3) {
        weight_grad_block<3>(z, a, out, in, k0, ob0, grad_wt);
      } else if (group == 2) {
        weight_grad_block<2>(z, a, out, in, k0, ob0, grad_wt);
      } else {
        weight_grad_block<1>(z, a, out, in, k0, ob0, grad_wt);
      }
    }
  }
}

// One tile of the forward: acts[0] rows [r0, r0 + kTile) from the input (zero-padded), then every
// layer; hidden layers write (after their ReLU) straight into the next layer's activation rows.
inline void forward_tile(const float* input, int64_t in_dim, const std::vector<Layer>& layers,
                         const std::vector<const float*>& weights_t, const std::vector<const float*>& biases,
                         const std::vector<float*>& acts, float* out, int64_t out_dim, int64_t n, int64_t r0,
                         float* scratch) {
  const int64_t kp0 = layers[0].in_padded;
  float* a0 = acts[0] + r0 * kp0;
  for (int64_t r = 0; r < kTile; ++r) {
    float* dst = a0 + r * kp0;
    const int64_t filled = r0 + r < n ? in_dim : 0;
    if (filled > 0) std::memcpy(dst, input + (r0 + r) * in_dim, filled * sizeof(float));
    std::fill(dst + filled, dst + kp0, 0.0f);
  }
  const int64_t num_layers = static_cast<int64_t>(layers.size());
  for (int64_t l = 0; l < num_layers; ++l) {
    const Layer& ly = layers[l];
    const float* a = acts[l] + r0 * ly.in_padded;
    if (l + 1 < num_layers) {
      gemm_tile(a, ly.in_padded, weights_t[l], ly.out_padded, ly.in_padded, biases[l], ly.relu,
                acts[l + 1] + r0 * ly.out_padded, ly.out_padded);
    } else {
      gemm_tile(a, ly.in_padded, weights_t[l], ly.out_padded, ly.in_padded, biases[l], false, scratch, ly.out_padded);
      for (int64_t r = 0; r < kTile && r0 + r < n; ++r)
        std::memcpy(out + (r0 + r) * out_dim, scratch + r * ly.out_padded, out_dim * sizeof(float));
    }
  }
}

// One tile of the inference forward: rows [r0, r0 + kTile) through every layer, the activations in
// the caller's per-thread tile buffers (bufs[l] [kTile, Kp_l] for l < L, bufs[L] [kTile, Op_last])
// instead of the [Npad, Kp_l] tensors the backward needs.
inline void infer_tile(const float* input, int64_t in_dim, const std::vector<Layer>& layers,
                       const std::vector<const float*>& weights_t, const std::vector<const float*>& biases,
                       const std::vector<float*>& bufs, float* out, int64_t out_dim, int64_t n, int64_t r0) {
  const int64_t kp0 = layers[0].in_padded;
  for (int64_t r = 0; r < kTile; ++r) {
    float* dst = bufs[0] + r * kp0;
    const int64_t filled = r0 + r < n ? in_dim : 0;
    if (filled > 0) std::memcpy(dst, input + (r0 + r) * in_dim, filled * sizeof(float));
    std::fill(dst + filled, dst + kp0, 0.0f);
  }
  const size_t num_layers = layers.size();
  for (size_t l = 0; l < num_layers; ++l) {
    const Layer& ly = layers[l];
    const bool last = l + 1 == num_layers;
    gemm_tile(bufs[l], ly.in_padded, weights_t[l], ly.out_padded, ly.in_padded, biases[l], ly.relu && !last, bufs[l + 1],
              ly.out_padded);
  }
  const int64_t last_out = layers.back().out_padded;
  for (int64_t r = 0; r < kTile && r0 + r < n; ++r)
    std::memcpy(out + (r0 + r) * out_dim, bufs[num_layers] + r * last_out, out_dim * sizeof(float));
}

// One tile of the backward: every layer's bias and weight gradients (added to grad_b, grad_wt)
// and, when grad_in is not null, the input gradient of rows [r0, r0 + kTile).
inline void backward_tile(const float* grad_out, int64_t out_dim, const std::vector<Layer>& layers,
                          const std::vector<const float*>& weights, const std::vector<const float*>& acts,
                          float* grad_in, int64_t in_dim, int64_t n, int64_t r0, const std::vector<float*>& grad_wt,
                          const std::vector<float*>& grad_b, TileScratch& s) {
  const int64_t num_layers = static_cast<int64_t>(layers.size());
  const int64_t last_out = layers.back().out_padded;
  float* dz = s.dz.data();
  float* da = s.da.data();
  for (int64_t r = 0; r < kTile; ++r) {
    float* dst = dz + r * last_out;
    const int64_t filled = r0 + r < n ? out_dim : 0;
    if (filled > 0) std::memcpy(dst, grad_out + (r0 + r) * out_dim, filled * sizeof(float));
    std::fill(dst + filled, dst + last_out, 0.0f);
  }
  for (int64_t l = num_layers - 1; l >= 0; --l) {
    const Layer& ly = layers[l];
    const int64_t op = ly.out_padded, kp = ly.in_padded;
    const float* a = acts[l] + r0 * kp;
    for (int64_t c = 0; c < op; c += 8) {  // bias gradient: column sums of dz
      V8 sum = load8(grad_b[l] + c);
      for (int64_t r = 0; r < kTile; ++r) sum += load8(dz + r * op + c);
      store8(grad_b[l] + c, sum);
    }
    weight_grad(dz, a, op, kp, grad_wt[l]);
    if (l == 0 && grad_in == nullptr) break;
    gemm_tile(dz, op, weights[l], kp, op, nullptr, false, da, kp);  // da = dz W
    if (l == 0) {
      for (int64_t r = 0; r < kTile && r0 + r < n; ++r)
        std::memcpy(grad_in + (r0 + r) * in_dim, da + r * kp, in_dim * sizeof(float));
      break;
    }
    if (layers[l - 1].relu) {  // through the previous layer's ReLU: its output is this layer's input a
      const V8 zero{};
      for (int64_t i = 0; i < kTile * kp; i += 8) {
        const V8 v = load8(da + i);
        store8(da + i, load8(a + i) <= zero ? zero : v);  // torch's threshold_backward: a NaN output passes
      }
    }
    std::swap(dz, da);
  }
}
