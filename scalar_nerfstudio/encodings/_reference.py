"""The test oracle of the hash-grid encoding: a straightforward per-level, per-vertex loop.

Kept apart from the production code (imported by tests and benchmarks only); it follows the
semantics written down in :mod:`scalar_nerfstudio.encodings.hash_grid`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from scalar_nerfstudio.encodings.hash_grid import PRIME_Y, PRIME_Z


def reference_hash_encoding(
    positions: Tensor, table: Tensor, *, level_offsets: Tensor, resolutions: Sequence[int], hashmap_size: int
) -> Tensor:
    """Straightforward per-level, per-vertex hash-grid encoding; the ground truth for tests.

    Differentiable w.r.t. ``table`` through ordinary autograd indexing. Slow; do not train with it.

    Args:
        positions: ``[N, 3]`` float32 in ``[0, 1]`` (NaN -> 0, others clamped).
        table: ``[sum_l rows_l, F]`` float32.
        level_offsets: ``[L + 1]`` int64, first row of each level and the total.
        resolutions: ``L`` ints ``R_l``.
        hashmap_size: ``T``, a power of two.

    Returns:
        ``[N, L * F]`` features, level-major (level ``l`` in columns ``l*F:(l+1)*F``).
    """
    p = torch.where(torch.isnan(positions), torch.zeros_like(positions), positions).clamp(0.0, 1.0)
    outputs = []
    for level, res in enumerate(resolutions):
        offset = int(level_offsets[level])
        scaled = p * res
        cell_f = torch.clamp(torch.floor(scaled), max=res - 1)
        frac = scaled - cell_f
        cell = cell_f.long()
        dense = (res + 1) ** 3 <= hashmap_size
        features = torch.zeros(p.shape[0], table.shape[1], dtype=table.dtype, device=table.device)
        for k in (0, 1):
            for j in (0, 1):
                for i in (0, 1):
                    x, y, z = cell[:, 0] + i, cell[:, 1] + j, cell[:, 2] + k
                    if dense:
                        row = x + y * (res + 1) + z * (res + 1) ** 2
                    else:
                        row = (x ^ (y * PRIME_Y) ^ (z * PRIME_Z)) % hashmap_size
                    wx = frac[:, 0] if i else 1.0 - frac[:, 0]
                    wy = frac[:, 1] if j else 1.0 - frac[:, 1]
                    wz = frac[:, 2] if k else 1.0 - frac[:, 2]
                    features = features + (wx * wy * wz)[:, None] * table[offset + row]
        outputs.append(features)
    return torch.cat(outputs, dim=-1)
