// Ray samples and the occupancy test in one pass each, CPU kernels with OpenMP.
//
// Registered as torch ops `torch.ops.scalar_nerf_sampling.unit_positions` and
// `torch.ops.scalar_nerf_sampling.worth_evaluating`; the Python side
// (`contract_rays_to_unit_cube` in fields/scalar_field.py, `OccupancyGrid` in
// model_components/sampling.py) calls them on the CPU and keeps its torch code as the path for
// CUDA and for a machine where the extension does not build. The torch code is what these
// kernels must agree with (tests/test_sampling_kernels.py):
//
//   unit_positions: p = o + d * t (world), q = (p - centre) / radius (the model's region frame),
//     x = q with NaN -> 0 and +-inf (and anything beyond) clamped to +-1e18, n = |x|,
//     contracted = x for n <= 1, x * (2 - 1/n) / n beyond; unit = clamp(contracted / 4 + 0.5, 0, 1).
//   worth_evaluating: cell = clamp(trunc(unit * G), 0, G - 1) per axis (NaN counts as 0),
//     flat = x * G^2 + y * G + z; worth = occupied[flat] and, when estimates are given,
//     (estimates[flat] * delta, NaN counted as +inf) >= min_optical_depth.
//
// Each is one pass over the samples with no temporaries: the torch code makes about ten passes
// over [R*S, 3] tensors (about 35 ms of a 192x128 view's ~320 ms on 2 cores).

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "check.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

namespace {

constexpr float kMaxCoordinate = 1e18f;
constexpr int64_t kGrain = 8192;

void check_cpu(const at::Tensor& t, const char* name, at::ScalarType type) {
  SCALAR_CHECK(t.device().is_cpu(), "scalar_nerf_sampling: ", name, " must be a CPU tensor, got ", t.device());
  SCALAR_CHECK(t.scalar_type() == type, "scalar_nerf_sampling: ", name, " must be ", type, ", got ", t.scalar_type());
  SCALAR_CHECK(t.is_contiguous(), "scalar_nerf_sampling: ", name, " must be contiguous");
}

// NaN -> 0, then clamped to +-kMaxCoordinate (infinities included); branch-free so that loops vectorise.
inline float sanitise(float v) {
  v = v != v ? 0.0f : v;
  return std::min(std::max(v, -kMaxCoordinate), kMaxCoordinate);
}

// origins [R, 3], directions [R, 3], t [R, S], centre [3] -> [R * S, 3] contracted unit-cube positions.
at::Tensor unit_positions(const at::Tensor& origins, const at::Tensor& directions, const at::Tensor& t,
                          const at::Tensor& centre, double radius) {
  check_cpu(origins, "origins", at::kFloat);
  check_cpu(directions, "directions", at::kFloat);
  check_cpu(t, "t", at::kFloat);
  check_cpu(centre, "centre", at::kFloat);
  SCALAR_CHECK(origins.dim() == 2 && origins.size(1) == 3, "scalar_nerf_sampling: origins must be [R, 3], got ",
               origins.sizes());
  SCALAR_CHECK(directions.sizes() == origins.sizes(), "scalar_nerf_sampling: directions must be ", origins.sizes(),
               ", got ", directions.sizes());
  SCALAR_CHECK(t.dim() == 2 && t.size(0) == origins.size(0), "scalar_nerf_sampling: t must be [R, S] with R = ",
               origins.size(0), ", got ", t.sizes());
  SCALAR_CHECK(centre.numel() == 3, "scalar_nerf_sampling: centre must have 3 values, got ", centre.numel());
  const int64_t num_rays = t.size(0);
  const int64_t num_samples = t.size(1);
  at::Tensor out = at::empty({num_rays * num_samples, 3}, origins.options());
  if (num_rays * num_samples == 0) return out;
  const float* o = origins.data_ptr<float>();
  const float* d = directions.data_ptr<float>();
  const float* ts = t.data_ptr<float>();
  const float* c = centre.data_ptr<float>();
  const float cx = c[0], cy = c[1], cz = c[2];
  const float r = static_cast<float>(radius);
  const bool identity = r == 1.0f && cx == 0.0f && cy == 0.0f && cz == 0.0f;
  float* u = out.data_ptr<float>();
  const int64_t grain = std::max<int64_t>(1, kGrain / std::max<int64_t>(num_samples, 1));
  at::parallel_for(0, num_rays, grain, [&](int64_t begin, int64_t end) {
    for (int64_t ray = begin; ray < end; ++ray) {
      const float ox = o[3 * ray], oy = o[3 * ray + 1], oz = o[3 * ray + 2];
      const float dx = d[3 * ray], dy = d[3 * ray + 1], dz = d[3 * ray + 2];
      for (int64_t s = 0; s < num_samples; ++s) {
        const int64_t i = ray * num_samples + s;
        const float ti = ts[i];
        float x = ox + dx * ti, y = oy + dy * ti, z = oz + dz * ti;
        if (!identity) {
          x = (x - cx) / r;
          y = (y - cy) / r;
          z = (z - cz) / r;
        }
        x = sanitise(x);
        y = sanitise(y);
        z = sanitise(z);
        const float norm = std::sqrt(x * x + y * y + z * z);
        const float inverse = 1.0f / std::max(norm, 1.0f);
        const float factor = norm <= 1.0f ? 1.0f : (2.0f - inverse) * inverse;
        // * 0.25f is exactly / 4
        u[3 * i] = std::min(std::max(x * factor * 0.25f + 0.5f, 0.0f), 1.0f);
        u[3 * i + 1] = std::min(std::max(y * factor * 0.25f + 0.5f, 0.0f), 1.0f);
        u[3 * i + 2] = std::min(std::max(z * factor * 0.25f + 0.5f, 0.0f), 1.0f);
      }
    }
  });
  return out;
}

inline int64_t cell_of(float v, float g) {
  v = v != v ? 0.0f : v;
  // torch's .long() truncates toward zero; values beyond the grid are clamped as floats first, so
  // that a huge value cannot overflow the integer conversion
  return static_cast<int64_t>(std::min(std::max(v * g, 0.0f), g - 1.0f));
}

// unit_positions [M, 3], deltas [M], occupied [G^3] bool, estimates [G^3] float or empty -> [M] bool.
at::Tensor worth_evaluating(const at::Tensor& unit_positions, const at::Tensor& deltas, const at::Tensor& occupied,
                            const at::Tensor& estimates, int64_t resolution, double min_optical_depth) {
  check_cpu(unit_positions, "unit_positions", at::kFloat);
  check_cpu(occupied, "occupied", at::kBool);
  SCALAR_CHECK(unit_positions.dim() == 2 && unit_positions.size(1) == 3,
               "scalar_nerf_sampling: unit_positions must be [M, 3], got ", unit_positions.sizes());
  SCALAR_CHECK(resolution > 0 && occupied.numel() == resolution * resolution * resolution,
               "scalar_nerf_sampling: occupied must have ", resolution, "^3 cells, got ", occupied.numel());
  const bool alpha_test = estimates.defined() && estimates.numel() > 0;
  const int64_t m = unit_positions.size(0);
  if (alpha_test) {
    check_cpu(estimates, "estimates", at::kFloat);
    check_cpu(deltas, "deltas", at::kFloat);
    SCALAR_CHECK(estimates.numel() == occupied.numel(), "scalar_nerf_sampling: estimates must have ", occupied.numel(),
                 " cells, got ", estimates.numel());
    SCALAR_CHECK(deltas.numel() == m, "scalar_nerf_sampling: deltas must have ", m, " values, got ", deltas.numel());
  }
  at::Tensor out = at::empty({m}, unit_positions.options().dtype(at::kBool));
  if (m == 0) return out;
  const float* u = unit_positions.data_ptr<float>();
  const bool* occ = occupied.data_ptr<bool>();
  const float* est = alpha_test ? estimates.data_ptr<float>() : nullptr;
  const float* del = alpha_test ? deltas.data_ptr<float>() : nullptr;
  const float min_depth = static_cast<float>(min_optical_depth);
  const int64_t g = resolution;
  const float gf = static_cast<float>(resolution);
  const float infinity = std::numeric_limits<float>::infinity();
  bool* w = out.data_ptr<bool>();
  at::parallel_for(0, m, kGrain, [&](int64_t begin, int64_t end) {
    if (alpha_test) {
      for (int64_t i = begin; i < end; ++i) {
        const int64_t cell = (cell_of(u[3 * i], gf) * g + cell_of(u[3 * i + 1], gf)) * g + cell_of(u[3 * i + 2], gf);
        // no branch on the occupancy (mispredicted about as often as cells are occupied)
        float depth = est[cell] * del[i];
        depth = depth != depth ? infinity : depth;
        w[i] = occ[cell] & (depth >= min_depth);
      }
    } else {
      for (int64_t i = begin; i < end; ++i) {
        w[i] = occ[(cell_of(u[3 * i], gf) * g + cell_of(u[3 * i + 1], gf)) * g + cell_of(u[3 * i + 2], gf)];
      }
    }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY(scalar_nerf_sampling, m) {
  m.def("unit_positions(Tensor origins, Tensor directions, Tensor t, Tensor centre, float radius) -> Tensor",
        &unit_positions);
  m.def(
      "worth_evaluating(Tensor unit_positions, Tensor deltas, Tensor occupied, Tensor estimates, int resolution, "
      "float min_optical_depth) -> Tensor",
      &worth_evaluating);
}
