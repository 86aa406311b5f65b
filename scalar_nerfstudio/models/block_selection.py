"""Which block renders which ray (per-ray block selection for fused rendering).

Each fusion mode uses some blocks on some rays (:func:`select_rays`); a block no ray chose is not
rendered at all, so a render costs the blocks chosen per ray, not the number of blocks. The modes
that score blocks by the surface a ray hits (``global``, ``idw``, ``surface``) read the global
model's depth, which the caller renders only when it is needed (``global_depth``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from scalar_nerfstudio.blocks.observation import observed_at
from scalar_nerfstudio.fusion import (
    ParsedFusionMode,
    nearest_block,
    nearest_blocks,
    region_scores,
    select_blocks,
    surface_points,
)


@dataclass(frozen=True, eq=False)  # eq=False: == on tensors is elementwise, so two records compare by identity
class BlockRegions:
    """Every block's region, indexed by block id: what :func:`select_rays` chooses a ray's blocks by.

    Attributes:
        centres: [K, 3] the blocks' centres.
        radii: [K] their radii (:func:`~scalar_nerfstudio.blocks.split.block_region`).
        observation: [K, G^3] bool, the cells each block's cameras observe (``blocks/observation.py``);
            None: blocks are chosen by their regions alone.
    """

    centres: Tensor
    radii: Tensor
    observation: Optional[Tensor] = None


def blocks_for(mode: ParsedFusionMode, started: Sequence[int]) -> List[int]:
    """Blocks that may render for ``mode``, of the ``started`` ones (none for global-only; for
    ``block:<k>`` block k alone if it has started)."""
    if mode.kind == "global-only":
        return []
    if mode.kind == "block":
        index = mode.block_index  # set for every "block" mode (parse_fusion_mode)
        return [index] if index is not None and index in started else []
    return list(started)


@torch.no_grad()
def select_rays(
    mode: ParsedFusionMode,
    block_ids: List[int],
    *,
    origins: Tensor,
    directions: Tensor,
    regions: BlockRegions,
    blocks_per_ray: int,
    global_depth: Callable[[], Tensor],
) -> Tuple[Tensor, Optional[Tensor]]:
    """Which of ``block_ids`` (K') renders which ray: ``([K', R] bool, [K', R] region scores or None)``.

    ``block``: every ray. ``nearest`` / ``nearest-guarded``: the block whose centre is nearest to the
    ray's origin; ``nearest-idw``: the ``blocks_per_ray`` blocks nearest to it (every block with 0).
    ``global`` / ``idw`` / ``surface``: the ``blocks_per_ray`` blocks whose region best holds the point
    at the global model's depth (:func:`region_scores`); with ``blocks_per_ray`` 0 or at least K',
    every block (``surface`` still weights them by score).

    Args:
        origins, directions: [R, 3] the rays.
        regions: every block's region (indexed by block id); with its ``observation``, a block is
            chosen only where it observes the surface point (a ray no block observes gets none),
            without it by region alone.
        blocks_per_ray: how many blocks per ray (0: every block).
        global_depth: renders the global model's depth [R, 1] of the rays, when the mode needs it.
    """
    num_rays, num_blocks = origins.shape[0], len(block_ids)
    every = torch.ones(num_blocks, num_rays, dtype=torch.bool, device=origins.device)
    if mode.kind == "block":
        return every, None
    centres = regions.centres[block_ids].to(origins.device)
    if mode.kind in ("nearest", "nearest-guarded"):
        nearest = nearest_block(origins, centres)
        return torch.arange(num_blocks, device=origins.device)[:, None] == nearest[None], None
    limit = blocks_per_ray
    if mode.kind == "nearest-idw":  # the blocks the weights will use: the `limit` nearest the origin
        return nearest_blocks(origins, centres, num_nearest=limit if limit > 0 else num_blocks), None
    if mode.kind != "surface" and (limit <= 0 or limit >= num_blocks):
        return every, None
    points = surface_points(origins, directions, global_depth())
    scores = region_scores(points, centres, regions.radii[block_ids].to(origins.device))
    usable = None
    if regions.observation is not None:
        usable = observed_at(regions.observation[block_ids], points).to(scores.device)  # [K', R]
        scores = torch.where(usable, scores, torch.full_like(scores, float("inf")))
    return select_blocks(scores, limit if limit > 0 else num_blocks, usable), scores
