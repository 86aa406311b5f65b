// What the hash grid's kernels accept, stated once for the C++ kernel (hash_grid.cpp) and the CUDA
// kernel (hash_grid_cuda.cu): the table's level layout and the tensors of a call. Every message
// starts with the kernel's name (`who`: "hash_grid cpp" or "hash_grid cuda") and names the numbers.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <vector>

#include "check.h"

namespace scalar_nerf {

// One level of the grid, checked against the table's layout.
struct LevelSpec {
  int64_t res;     // R_l, in [1, 2^24)
  int64_t offset;  // first row of the level in the flat table
  int64_t rows;    // (R_l + 1)^3 when dense, else T
  bool dense;      // (R_l + 1)^3 <= T: one row per vertex, no hashing
};

// The levels of a table of `table_rows` rows; level l owns rows [level_offsets[l], level_offsets[l + 1]).
inline std::vector<LevelSpec> level_specs(at::IntArrayRef level_offsets, at::IntArrayRef resolutions,
                                          int64_t hashmap_size, int64_t table_rows, const char* who) {
  const int64_t num_levels = static_cast<int64_t>(resolutions.size());
  SCALAR_CHECK(num_levels >= 1, who, ": need at least one level");
  SCALAR_CHECK(static_cast<int64_t>(level_offsets.size()) == num_levels + 1, who,
               ": level_offsets must have num_levels + 1 entries");
  SCALAR_CHECK(hashmap_size >= 1 && hashmap_size <= (int64_t{1} << 31) && (hashmap_size & (hashmap_size - 1)) == 0,
               who, ": hashmap_size must be a power of two <= 2^31, got ", hashmap_size);
  SCALAR_CHECK(level_offsets[0] == 0 && level_offsets[num_levels] == table_rows, who,
               ": level_offsets must start at 0 and end at the table's row count (", table_rows, ")");
  std::vector<LevelSpec> levels(num_levels);
  for (int64_t l = 0; l < num_levels; ++l) {
    const int64_t res = resolutions[l];
    SCALAR_CHECK(res >= 1 && res < (int64_t{1} << 24), who, ": resolution must be in [1, 2^24), got ", res);
    const int64_t verts = (res + 1) * (res + 1) * (res + 1);
    LevelSpec& level = levels[l];
    level.res = res;
    level.dense = verts <= hashmap_size;
    level.offset = level_offsets[l];
    level.rows = level_offsets[l + 1] - level_offsets[l];
    const int64_t expected = level.dense ? verts : hashmap_size;
    SCALAR_CHECK(level.rows == expected, who, ": level ", l, " has ", level.rows, " rows, expected ", expected);
  }
  return levels;
}

// A contiguous 2-D float32 tensor on the kernel's device (the CPU, or CUDA when `cuda`).
inline void check_float_matrix(const at::Tensor& t, const char* name, bool cuda, const char* who) {
  if (cuda) {
    SCALAR_CHECK(t.device().is_cuda(), who, ": ", name, " must be a CUDA tensor, got ", t.device());
  } else {
    SCALAR_CHECK(t.device().is_cpu(), who, ": ", name, " must be a CPU tensor, got ", t.device());
  }
  SCALAR_CHECK(t.scalar_type() == at::kFloat, who, ": ", name, " must be float32, got ", t.scalar_type());
  SCALAR_CHECK(t.dim() == 2, who, ": ", name, " must be 2-D, got shape ", t.sizes());
  SCALAR_CHECK(t.is_contiguous(), who, ": ", name, " must be contiguous");
}

// positions [N, 3] on the kernel's device.
inline void check_positions(const at::Tensor& positions, bool cuda, const char* who) {
  check_float_matrix(positions, "positions", cuda, who);
  SCALAR_CHECK(positions.size(1) == 3, who, ": positions must be [N, 3], got ", positions.sizes());
}

// F, the features per table row: the kernels are specialised for 1, 2, 4 and 8.
inline void check_features(int64_t f, const char* who) {
  SCALAR_CHECK(f == 1 || f == 2 || f == 4 || f == 8, who, ": features_per_level must be 1, 2, 4 or 8, got ", f);
}

// The table's row count of a backward call (which has no table): the last level offset.
inline int64_t table_rows_of(at::IntArrayRef level_offsets, const char* who) {
  SCALAR_CHECK(!level_offsets.empty(), who, ": level_offsets must not be empty");
  return level_offsets.back();
}

// grad_out [N, L * F] of a backward call for n points.
inline void check_grad_out(const at::Tensor& grad_out, int64_t n, int64_t num_levels, int64_t f, bool cuda,
                           const char* who) {
  check_float_matrix(grad_out, "grad_out", cuda, who);
  SCALAR_CHECK(grad_out.size(0) == n && grad_out.size(1) == num_levels * f, who,
               ": grad_out must be [N, num_levels * F], got ", grad_out.sizes());
}

// A forward call: positions [N, 3] and table [rows, F] on one device of the kernel's kind. Returns F.
inline int64_t check_forward_call(const at::Tensor& positions, const at::Tensor& table, bool cuda, const char* who) {
  check_positions(positions, cuda, who);
  check_float_matrix(table, "table", cuda, who);
  SCALAR_CHECK(table.device() == positions.device(), who, ": table is on ", table.device(), ", positions on ",
               positions.device());
  check_features(table.size(1), who);
  return table.size(1);
}

// A backward call: positions [N, 3] and grad_out [N, L * F] on one device of the kernel's kind.
// Returns the table's row count.
inline int64_t check_backward_call(const at::Tensor& grad_out, const at::Tensor& positions, at::IntArrayRef level_offsets,
                                   int64_t num_levels, int64_t f, bool cuda, const char* who) {
  check_positions(positions, cuda, who);
  check_features(f, who);
  check_grad_out(grad_out, positions.size(0), num_levels, f, cuda, who);
  SCALAR_CHECK(grad_out.device() == positions.device(), who, ": grad_out is on ", grad_out.device(),
               ", positions on ", positions.device());
  return table_rows_of(level_offsets, who);
}

}  // namespace scalar_nerf
