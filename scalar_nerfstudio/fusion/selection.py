"""Which blocks a ray may take its colour from: the surface point the global depth gives, each
block's region score of it, the lowest scores per ray, or the blocks whose centres are nearest the
camera (torch only)."""

from __future__ import annotations

import torch
from torch import Tensor

from scalar_nerfstudio.fusion.numerics import broadcast_valid, compute_dtype, distances


def surface_points(origins: Tensor, directions: Tensor, depth: Tensor) -> Tensor:
    """``[N, 3]`` points ``o + t d`` at the depth ``t`` ``[N]`` or ``[N, 1]`` along each ray.

    A depth that is NaN, negative or infinite (nothing hit, a failed render) gives the ray's origin,
    so every point is finite for finite rays.
    """
    depth = depth.reshape(-1, 1).to(origins.dtype)
    if depth.shape[0] != origins.shape[0] or origins.shape != directions.shape:
        raise ValueError(f"origins {list(origins.shape)}, directions {list(directions.shape)} and depth {list(depth.shape)} must agree")
    depth = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth))
    return origins + directions * depth


def region_scores(points: Tensor, centres: Tensor, radii: Tensor) -> Tensor:
    """``[K, N]`` score of each point in each block's region: ``max_i |x_i - c_i| / r``.

    Args:
        points: ``[N, 3]`` world points (e.g. :func:`surface_points`).
        centres: ``[K, 3]`` region centres, same frame.
        radii: ``[K]`` region half-sizes (> 0): the cube a block's hash grid resolves at full resolution.

    Returns:
        ``[K, N]`` float32 (or wider) scores, ``<= 1`` inside the cube, growing with the distance from it
        in units of the block's size; ``inf`` for a non-finite point.
    """
    if centres.ndim != 2 or centres.shape[1] != 3 or radii.shape != centres.shape[:1]:
        raise ValueError(f"centres must be [K, 3] and radii [K], got {list(centres.shape)} and {list(radii.shape)}")
    if not bool((radii > 0).all()) or not bool(torch.isfinite(radii).all()):
        raise ValueError("region radii must be finite and > 0")
    dtype = compute_dtype(points, centres, radii)
    offsets = (points.to(dtype)[None] - centres.to(device=points.device, dtype=dtype)[:, None]).abs()  # [K, N, 3]
    scores = offsets.amax(dim=-1) / radii.to(device=points.device, dtype=dtype)[:, None]
    return torch.where(torch.isfinite(scores), scores, torch.full_like(scores, float("inf")))


def select_blocks(scores: Tensor, blocks_per_ray: int, usable: Tensor | None = None) -> Tensor:
    """``[K, N]`` bool: per pixel, the ``blocks_per_ray`` usable blocks of lowest score.

    Ties go to the lower block index. NaN scores count as ``inf``. ``usable`` (``[K]`` or ``[K, N]``)
    excludes blocks; with ``blocks_per_ray >= K`` every usable block is selected.
    """
    if blocks_per_ray < 1:
        raise ValueError(f"blocks_per_ray must be >= 1, got {blocks_per_ray}")
    if scores.ndim != 2:
        raise ValueError(f"scores must have shape [K, N], got {list(scores.shape)}")
    mask = broadcast_valid(usable, scores.shape, scores.device)
    ranked = torch.where(mask, torch.nan_to_num(scores, nan=float("inf")), torch.full_like(scores, float("inf")))
    if blocks_per_ray >= scores.shape[0]:
        return mask.clone()
    order = torch.sort(ranked, dim=0, stable=True).indices[:blocks_per_ray]  # [M, N]
    selected = torch.zeros_like(mask)
    selected.scatter_(0, order, torch.ones_like(order, dtype=torch.bool))
    return selected & mask



def nearest_block(camera_origin: Tensor, block_centres: Tensor, valid: Tensor | None = None) -> Tensor:
    """Index of the valid block centre nearest to the camera origin.

    Args:
        camera_origin: ``[3]`` or ``[N, 3]`` positions.
        block_centres: ``[K, 3]`` block centres (same frame and units).
        valid: Optional ``[K]`` or ``[K, N]`` bool mask of usable blocks.

    Returns:
        int64 tensor, ``[]`` for one origin or ``[N]``: ties go to the lowest index;
        ``-1`` where no block is valid.
    """
    dist = distances(camera_origin, block_centres)
    valid_mask = broadcast_valid(valid, dist.shape, dist.device)
    dist = torch.where(valid_mask, dist, torch.full_like(dist, float("inf")))
    index = torch.argmin(dist, dim=0)
    return torch.where(valid_mask.any(dim=0), index, torch.full_like(index, -1))


def nearest_blocks(camera_origin: Tensor, block_centres: Tensor, *, num_nearest: int | None, valid: Tensor | None = None) -> Tensor:
    """``[K]`` or ``[K, N]`` bool: the ``num_nearest`` valid blocks whose centres are nearest the camera.

    Args:
        camera_origin: ``[3]`` (one camera) or ``[N, 3]`` (per ray) positions.
        block_centres: ``[K, 3]`` block centres, same frame and units as the origin.
        num_nearest: how many blocks (>= 1); with ``>= K`` or None every valid block.
        valid: optional ``[K]`` or ``[K, N]`` bool; invalid blocks are never chosen.

    Ties in distance go to the lower block index; nothing is chosen where no block is valid.
    """
    return nearest_of(distances(camera_origin, block_centres), num_nearest, valid)


def nearest_of(dist: Tensor, num_nearest: int | None, valid: Tensor | None) -> Tensor:
    """:func:`nearest_blocks` from the ``[K]`` or ``[K, N]`` distances."""
    valid_mask = broadcast_valid(valid, dist.shape, dist.device)
    if num_nearest is None:
        return valid_mask
    if num_nearest < 1:
        raise ValueError(f"num_nearest must be >= 1, got {num_nearest}")
    flat = (dist.shape[0], -1)
    return select_blocks(dist.reshape(flat), num_nearest, valid_mask.reshape(flat)).reshape(dist.shape)

