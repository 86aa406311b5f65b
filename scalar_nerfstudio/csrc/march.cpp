// The render march without gradients: front-to-back rounds of candidates and compact volume rendering,
// CPU kernels registered as `torch.ops.scalar_nerf_march.*`.
//
// The Python side (`VisibilitySampler.visible_with_features` in model_components/visibility.py and
// `render_kept_samples` in model_components/rendering.py) keeps its torch code as the path for CUDA, for
// gradients and for a machine where the extension does not build; these kernels must agree with it
// (tests/test_march_kernels.py):
//
//   round_candidates: the rays still lit (counts[r] > rank and -depth_before[r] > log_threshold) and, for each,
//     its candidates rank .. rank + group - 1 that exist: (ids [N] flat sample ids, rays [N]), ray-major.
//   round_keep: over one round's candidates with their density, per ray in order, the optical depth in front
//     of each (depth_before[r] plus the sum of the round's earlier ones), keep = exp(-before) > threshold and
//     alpha > min_alpha; depth_before[r] advances by the round's sum.
//   composite: the kept samples of each ray in front-to-back order (rays may interleave) -> weights
//     w = clamp(T * alpha, 0, 1) with T = exp(-optical depth in front), rgb = sum w c + (1 - acc) background,
//     depth = sum w t / acc (far where acc <= 1e-10), at most far.
//   alpha = 1 - exp(-clamp(nan->0(density) * delta, 0, 50)); optical depth = -log1p(-clamp(alpha, 0, 1 - 1e-7)),
//   as alphas_from_densities / weights_from_alphas in model_components/rendering.py.
//
// Each replaces a dozen torch passes over [R, S] or [A, group] tensors with one pass over what is kept.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include "check.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <tuple>
#include <vector>

namespace {

constexpr float kMaxOpticalDepth = 50.0f;
constexpr float kMaxAlpha = 1.0f - 1e-7f;
constexpr int64_t kGrain = 4096;
constexpr float kInfinity = std::numeric_limits<float>::infinity();

void check_cpu(const at::Tensor& t, const char* name, at::ScalarType type, int64_t dim) {
  SCALAR_CHECK(t.device().is_cpu(), "scalar_nerf_march: ", name, " must be a CPU tensor, got ", t.device());
  SCALAR_CHECK(t.scalar_type() == type, "scalar_nerf_march: ", name, " must be ", type, ", got ", t.scalar_type());
  SCALAR_CHECK(t.is_contiguous(), "scalar_nerf_march: ", name, " must be contiguous");
  SCALAR_CHECK(t.dim() == dim, "scalar_nerf_march: ", name, " must have ", dim, " dimensions, got ", t.sizes());
}

inline float alpha_of(float density, float delta) {
  float depth = (density != density ? 0.0f : density) * delta;
  depth = depth != depth ? 0.0f : std::min(std::max(depth, 0.0f), kMaxOpticalDepth);  // NaN: 0 * inf (torch: NaN)
  return 1.0f - std::exp(-depth);
}

inline float optical_of(float alpha) { return -std::log1p(-std::min(std::max(alpha, 0.0f), kMaxAlpha)); }

std::tuple<at::Tensor, at::Tensor> round_candidates(const at::Tensor& counts, const at::Tensor& firsts,
                                                    const at::Tensor& candidate_ids, const at::Tensor& depth_before,
                                                    int64_t rank, int64_t group, double log_threshold) {
  check_cpu(counts, "counts", at::kLong, 1);
  check_cpu(firsts, "firsts", at::kLong, 1);
  check_cpu(candidate_ids, "candidate_ids", at::kLong, 1);
  check_cpu(depth_before, "depth_before", at::kFloat, 1);
  const int64_t num_rays = counts.size(0);
  SCALAR_CHECK(firsts.size(0) == num_rays && depth_before.size(0) == num_rays,
               "scalar_nerf_march: counts, firsts and depth_before must have one value per ray, got ", num_rays, ", ",
               firsts.size(0), " and ", depth_before.size(0));
  SCALAR_CHECK(rank >= 0 && group > 0, "scalar_nerf_march: rank must be >= 0 and group > 0, got ", rank, " and ", group);
  const int64_t* count = counts.data_ptr<int64_t>();
  const int64_t* first = firsts.data_ptr<int64_t>();
  const int64_t* candidates = candidate_ids.data_ptr<int64_t>();
  const int64_t num_candidates = candidate_ids.size(0);
  const float* depth = depth_before.data_ptr<float>();
  const float limit = static_cast<float>(log_threshold);
  int64_t total = 0;
  for (int64_t r = 0; r < num_rays; ++r) {
    if (count[r] > rank && -depth[r] > limit) total += std::min(group, count[r] - rank);
  }
  at::Tensor ids = at::empty({total}, candidate_ids.options());
  at::Tensor rays = at::empty({total}, candidate_ids.options());
  int64_t* id_out = ids.data_ptr<int64_t>();
  int64_t* ray_out = rays.data_ptr<int64_t>();
  int64_t n = 0;
  for (int64_t r = 0; r < num_rays; ++r) {
    if (!(count[r] > rank && -depth[r] > limit)) continue;
    const int64_t end = std::min(count[r], rank + group);
    SCALAR_CHECK(first[r] >= 0 && first[r] + end <= num_candidates, "scalar_nerf_march: ray ", r,
                 "'s candidates lie outside candidate_ids (", num_candidates, " values)");
    for (int64_t j = rank; j < end; ++j) {
      id_out[n] = candidates[first[r] + j];
      ray_out[n] = r;
      ++n;
    }
  }
  return {ids, rays};
}

at::Tensor round_keep(const at::Tensor& ids, const at::Tensor& rays, const at::Tensor& density, const at::Tensor& deltas,
                      at::Tensor& depth_before, double threshold, double min_alpha) {
  check_cpu(ids, "ids", at::kLong, 1);
  check_cpu(rays, "rays", at::kLong, 1);
  check_cpu(density, "density", at::kFloat, 1);
  check_cpu(deltas, "deltas", at::kFloat, 1);
  check_cpu(depth_before, "depth_before", at::kFloat, 1);
  const int64_t n = ids.size(0);
  SCALAR_CHECK(rays.size(0) == n && density.size(0) == n, "scalar_nerf_march: ids, rays and density must have the same length, got ",
               n, ", ", rays.size(0), " and ", density.size(0));
  const int64_t num_samples = deltas.size(0);
  const int64_t num_rays = depth_before.size(0);
  const int64_t* id = ids.data_ptr<int64_t>();
  const int64_t* ray = rays.data_ptr<int64_t>();
  const float* sigma = density.data_ptr<float>();
  const float* delta = deltas.data_ptr<float>();
  float* depth = depth_before.data_ptr<float>();
  const float keep_above = static_cast<float>(threshold);
  const float alpha_above = static_cast<float>(min_alpha);
  for (int64_t i = 0; i < n; ++i) {  // checked before the parallel pass, so that a bad input raises here
    SCALAR_CHECK(ray[i] >= 0 && ray[i] < num_rays, "scalar_nerf_march: ray index ", ray[i], " outside [0, ", num_rays, ")");
    SCALAR_CHECK(i == 0 || ray[i] >= ray[i - 1], "scalar_nerf_march: round_keep's rays must be in ray-major order");
    SCALAR_CHECK(id[i] >= 0 && id[i] < num_samples, "scalar_nerf_march: sample id ", id[i], " outside [0, ", num_samples, ")");
  }
  at::Tensor keep = at::empty({n}, ids.options().dtype(at::kBool));
  bool* kept = keep.data_ptr<bool>();
  at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
    // whole rays only: from the first ray that starts at or after `begin` to the first that starts at or after `end`
    int64_t i = begin;
    while (i > 0 && i < n && ray[i] == ray[i - 1]) ++i;
    int64_t stop = end;
    while (stop < n && ray[stop] == ray[stop - 1]) ++stop;
    while (i < stop) {
      const int64_t r = ray[i];
      const float start = depth[r];
      float sum = 0.0f;  // the round's optical depth so far (torch: cumsum over the round, then + depth_before)
      bool leading = true;
      for (; i < stop && ray[i] == r; ++i) {
        const float alpha = alpha_of(sigma[i], delta[id[i]]);
        const float before = leading ? start : sum + start;
        kept[i] = std::exp(-before) > keep_above && alpha > alpha_above;
        sum += optical_of(alpha);
        leading = false;
      }
      depth[r] = sum + start;
    }
  });
  return keep;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> composite(
    const at::Tensor& sample_ids, const at::Tensor& density, const at::Tensor& rgb, const at::Tensor& deltas,
    const at::Tensor& t_mid, const at::Tensor& fars, const at::Tensor& background) {
  check_cpu(sample_ids, "sample_ids", at::kLong, 1);
  check_cpu(density, "density", at::kFloat, 1);
  check_cpu(rgb, "rgb", at::kFloat, 2);
  check_cpu(deltas, "deltas", at::kFloat, 2);
  check_cpu(t_mid, "t_mid", at::kFloat, 2);
  check_cpu(fars, "fars", at::kFloat, 1);
  check_cpu(background, "background", at::kFloat, 2);
  const int64_t m = sample_ids.size(0);
  const int64_t num_rays = deltas.size(0);
  const int64_t num_samples = deltas.size(1);
  SCALAR_CHECK(density.size(0) == m && rgb.size(0) == m && rgb.size(1) == 3,
               "scalar_nerf_march: density must be [M] and rgb [M, 3] with M = ", m, ", got ", density.sizes(), " and ", rgb.sizes());
  SCALAR_CHECK(t_mid.sizes() == deltas.sizes(), "scalar_nerf_march: t_mid must be ", deltas.sizes(), ", got ", t_mid.sizes());
  SCALAR_CHECK(fars.size(0) == num_rays && background.size(0) == num_rays && background.size(1) == 3,
               "scalar_nerf_march: fars must be [R] and background [R, 3] with R = ", num_rays, ", got ", fars.sizes(), " and ",
               background.sizes());
  const int64_t* id = sample_ids.data_ptr<int64_t>();
  const float* sigma = density.data_ptr<float>();
  const float* colour = rgb.data_ptr<float>();
  const float* delta = deltas.data_ptr<float>();
  const float* t = t_mid.data_ptr<float>();
  const float* far = fars.data_ptr<float>();
  const float* back = background.data_ptr<float>();
  at::Tensor rgb_out = at::zeros({num_rays, 3}, rgb.options());
  at::Tensor depth_out = at::empty({num_rays, 1}, rgb.options());
  at::Tensor accumulation_out = at::zeros({num_rays, 1}, rgb.options());
  at::Tensor weights_out = at::empty({m}, rgb.options());
  float* out_rgb = rgb_out.data_ptr<float>();
  float* out_depth = depth_out.data_ptr<float>();
  float* out_acc = accumulation_out.data_ptr<float>();
  float* out_weight = weights_out.data_ptr<float>();
  {  // checked before the parallel pass, so that a bad input raises here
    std::vector<int64_t> last(num_rays, -1);  // each ray's last sample so far
    for (int64_t i = 0; i < m; ++i) {
      const int64_t s = id[i];
      SCALAR_CHECK(s >= 0 && s < num_rays * num_samples, "scalar_nerf_march: sample id ", s, " outside [0, ",
                   num_rays * num_samples, ")");
      const int64_t r = s / num_samples;
      SCALAR_CHECK(s > last[r], "scalar_nerf_march: the samples of ray ", r, " are not in front-to-back order (", s, " after ",
                   last[r], ")");
      last[r] = s;
    }
  }
  // Each thread takes a range of rays and reads every sample id, compositing those of its rays (rays interleave).
  at::parallel_for(0, num_rays, kGrain, [&](int64_t ray_begin, int64_t ray_end) {
    std::vector<float> optical(ray_end - ray_begin, 0.0f);     // optical depth in front of each ray's next sample
    std::vector<float> weighted_t(ray_end - ray_begin, 0.0f);  // sum w t
    const int64_t low = ray_begin * num_samples, high = ray_end * num_samples;
    for (int64_t i = 0; i < m; ++i) {
      const int64_t s = id[i];
      if (s < low || s >= high) continue;
      const int64_t r = s / num_samples;
      const int64_t local = r - ray_begin;
      const float alpha = alpha_of(sigma[i], delta[s]);
      const float w = std::min(std::max(std::exp(-optical[local]) * alpha, 0.0f), 1.0f);
      optical[local] += optical_of(alpha);
      out_weight[i] = w;
      out_acc[r] += w;
      weighted_t[local] += w * t[s];
      out_rgb[3 * r] += w * colour[3 * i];
      out_rgb[3 * r + 1] += w * colour[3 * i + 1];
      out_rgb[3 * r + 2] += w * colour[3 * i + 2];
    }
    for (int64_t r = ray_begin; r < ray_end; ++r) {
      const float acc = out_acc[r];
      float d = acc > 1e-10f ? weighted_t[r - ray_begin] / std::max(acc, 1e-10f) : far[r];
      d = d != d || d == kInfinity ? 0.0f : (d == -kInfinity ? std::numeric_limits<float>::lowest() : d);  // torch.nan_to_num
      out_depth[r] = std::min(d, far[r]);
      for (int c = 0; c < 3; ++c) out_rgb[3 * r + c] += (1.0f - acc) * back[3 * r + c];
    }
  });
  return {rgb_out, depth_out, accumulation_out, weights_out};
}

}  // namespace

TORCH_LIBRARY(scalar_nerf_march, m) {
  m.def(
      "round_candidates(Tensor counts, Tensor firsts, Tensor candidate_ids, Tensor depth_before, int rank, int group, "
      "float log_threshold) -> (Tensor, Tensor)",
      &round_candidates);
  m.def(
      "round_keep(Tensor ids, Tensor rays, Tensor density, Tensor deltas, Tensor(a!) depth_before, float threshold, "
      "float min_alpha) -> Tensor",
      &round_keep);
  m.def(
      "composite(Tensor sample_ids, Tensor density, Tensor rgb, Tensor deltas, Tensor t_mid, Tensor fars, Tensor background) "
      "-> (Tensor, Tensor, Tensor, Tensor)",
      &composite);
}
