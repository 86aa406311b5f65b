"""The fusion rules: per-pixel block weights of every fusion mode (:func:`fusion_weights`), one-hot
for the winner modes, and the guard of ``nearest-guarded`` (torch only)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from scalar_nerfstudio.fusion.blend import fuse_weighted, select_winner
from scalar_nerfstudio.fusion.modes import ParsedFusionMode, parse_fusion_mode
from scalar_nerfstudio.fusion.numerics import (
    check_block_values,
    check_gamma,
    distances,
    inverse_distance_shares,
    usable_mask,
)
from scalar_nerfstudio.fusion.selection import nearest_block, nearest_of, select_blocks


def fuse_global_guided(
    block_rgb: Tensor, global_rgb: Tensor, valid: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Pick, per pixel, the block colour closest (L2) to the global model's colour.

    Args:
        block_rgb: ``[K, N, 3]`` block colours.
        global_rgb: ``[N, 3]`` coarse global model colours.
        valid: Optional ``[K, N]`` bool; ``False`` excludes a block at a pixel.

    Returns:
        ``(fused_rgb [N, 3], winner [N] int64)``.  Ties go to the lowest block index.  A
        block whose colour is NaN/inf or not valid is never chosen; where no block is
        usable the global colour is returned and ``winner == -1``.  Where the global
        colour itself is NaN/inf the lowest-index usable block wins.
    """
    check_block_values(block_rgb, "block_rgb")
    if global_rgb.shape != block_rgb.shape[1:]:
        raise ValueError(f"global_rgb must have shape {list(block_rgb.shape[1:])}, got {list(global_rgb.shape)}")
    usable = usable_mask(block_rgb, valid)
    diff = torch.where(usable[..., None], block_rgb - global_rgb[None], torch.zeros_like(block_rgb))
    dist = (diff * diff).sum(dim=-1)
    dist = torch.where(torch.isfinite(global_rgb).all(dim=-1)[None], dist, torch.zeros_like(dist))
    dist = torch.where(usable & torch.isfinite(dist), dist, torch.full_like(dist, float("inf")))
    winner = torch.argmin(dist, dim=0)  # first minimum -> lowest index on ties
    winner = torch.where(torch.isfinite(dist).any(dim=0), winner, torch.full_like(winner, -1))
    return select_winner(block_rgb, winner, fallback=global_rgb), winner


def idw_weights(
    camera_origin: Tensor, block_centres: Tensor, *, gamma: float = 1.0, valid: Tensor | None = None
) -> Tensor:
    """Inverse-distance weights ``w_k = d_k^-gamma / sum_j d_j^-gamma`` (Eq. idw).

    Args:
        camera_origin: ``[3]`` (one camera) or ``[N, 3]`` (per ray) positions.
        block_centres: ``[K, 3]`` block centres, same frame and units as the origin.
        gamma: Exponent ``>= 0``; ``0`` gives uniform weights over the valid blocks.
        valid: Optional ``[K]`` or ``[K, N]`` bool; invalid blocks get weight 0.

    Returns:
        ``[K]`` or ``[K, N]`` weights (dtype of ``block_centres`` if floating, else float32),
        summing to one over K.  A camera exactly at one or more valid block centres gives
        those blocks equal shares of all the weight (no division by zero).  Where no block
        is valid all weights are 0.
    """
    return nearest_idw_weights(camera_origin, block_centres, num_nearest=None, gamma=gamma, valid=valid)


def score_weights(scores: Tensor, selected: Tensor, gamma: float = 1.0) -> Tensor:
    """``[K, N]`` weights of the ``surface`` rule: ``score^-gamma`` over the selected blocks, summing to one.

    A score of 0 (the point at a block's centre) takes all the weight; pixels with nothing selected
    get all-zero weights (the caller's fallback).
    """
    return inverse_distance_shares(torch.nan_to_num(scores, nan=float("inf")), selected, check_gamma(gamma))


def nearest_idw_weights(
    camera_origin: Tensor, block_centres: Tensor, *, num_nearest: int | None, gamma: float = 2.0, valid: Tensor | None = None
) -> Tensor:
    """Inverse-distance weights over the ``num_nearest`` valid blocks nearest to the camera (``nearest-idw``).

    Args:
        camera_origin: ``[3]`` (one camera) or ``[N, 3]`` (per ray) positions.
        block_centres: ``[K, 3]`` block centres, same frame and units as the origin.
        num_nearest: how many of the nearest valid blocks share the weight (>= 1); with 1 this is
            :func:`nearest_block` as one-hot weights, with ``>= K`` or None it is :func:`idw_weights`.
        gamma: exponent ``>= 0`` of the inverse distance.
        valid: optional ``[K]`` or ``[K, N]`` bool; invalid blocks are neither chosen nor weighted.

    Returns:
        ``[K]`` or ``[K, N]`` weights summing to one over K (dtype of ``block_centres`` if floating, else
        float32); ties in distance go to the lower block index; all zero where no block is valid. A
        camera at a block's centre gives that block all the weight.
    """
    gamma = check_gamma(gamma)
    dist = distances(camera_origin, block_centres)
    weights = inverse_distance_shares(dist, nearest_of(dist, num_nearest, valid), gamma)
    out_dtype = block_centres.dtype if block_centres.is_floating_point() else torch.float32
    return weights.to(out_dtype)


def transparent_pixels(weights: Tensor, block_accumulation: Tensor, threshold: float = 0.5) -> Tensor:
    """The pixels whose blocks give no opaque render: ``[N]`` bool, True where the accumulation the
    fused blocks give (weighted as :func:`fuse_weighted` weights them) is below ``threshold`` or where
    no block gives a usable (finite) one. The pixels :func:`guard_transparent` may hand to the global
    model, so the ones it must have rendered.

    Args:
        weights: ``[K, N]`` fusion weights (:func:`fusion_weights`).
        block_accumulation: ``[K, N]`` or ``[K, N, 1]`` each block's accumulation; NaN where a block
            was not rendered.
        threshold: in (0, 1].
    """
    if not (isinstance(threshold, (int, float)) and math.isfinite(threshold) and 0.0 < threshold <= 1.0):
        raise ValueError(f"threshold must be a number in (0, 1], got {threshold!r}")
    if weights.ndim != 2:
        raise ValueError(f"weights must have shape [K, N], got {list(weights.shape)}")
    num_blocks, num_pixels = weights.shape
    if block_accumulation.shape not in ((num_blocks, num_pixels), (num_blocks, num_pixels, 1)):
        raise ValueError(f"block_accumulation must have shape [{num_blocks}, {num_pixels}(, 1)], got {list(block_accumulation.shape)}")
    given = fuse_weighted(block_accumulation.reshape(num_blocks, num_pixels, 1), weights)[:, 0]  # [N]; NaN where no block
    return ~(given >= threshold)  # NaN compares False: no usable block counts as transparent


def guard_transparent(
    weights: Tensor, block_accumulation: Tensor, global_accumulation: Tensor, *, threshold: float = 0.5
) -> Tensor:
    """``nearest-guarded``: take the blocks out of the pixels where what they give is transparent
    (:func:`transparent_pixels`: accumulated opacity below ``threshold``, or no usable block) and the
    global model's render opaque (at least ``threshold``).

    Args:
        weights: ``[K, N]`` fusion weights (:func:`fusion_weights`).
        block_accumulation: ``[K, N]`` or ``[K, N, 1]`` each block's accumulation; NaN where a block
            was not rendered.
        global_accumulation: ``[N]`` or ``[N, 1]`` the global model's; NaN where it was not rendered
            (no guard there).
        threshold: in (0, 1].

    Returns:
        ``[K, N]`` weights, all zero at the guarded pixels: :func:`fuse_weighted` gives them the
        global model's values (its ``fallback``), and :func:`weights_winner` -1.
    """
    transparent = transparent_pixels(weights, block_accumulation, threshold)  # validates all but the global model's
    num_pixels = weights.shape[1]
    if global_accumulation.shape not in ((num_pixels,), (num_pixels, 1)):
        raise ValueError(f"global_accumulation must have shape [{num_pixels}(, 1)], got {list(global_accumulation.shape)}")
    opaque = global_accumulation.reshape(num_pixels).to(transparent.device) >= threshold  # NaN compares False: no guard
    return torch.where((transparent & opaque)[None], torch.zeros_like(weights), weights)


def _per_pixel(index: Tensor, num_pixels: int) -> Tensor:
    """Broadcast a scalar or ``[N]`` block index to ``[N]`` int64."""
    return index.to(torch.long).reshape(-1).expand(num_pixels) if index.numel() == 1 else index.to(torch.long)


def fusion_weights(
    mode: str | ParsedFusionMode,
    block_rgb: Tensor,
    global_rgb: Tensor | None = None,
    *,
    camera_origin: Tensor | None = None,
    block_centres: Tensor | None = None,
    gamma: float = 1.0,
    block_scores: Tensor | None = None,
    blocks_per_ray: int | None = None,
) -> Tensor:
    """``[K, N]`` per-pixel block weights of a fusion mode (one-hot for global / nearest / block).

    Args:
        mode: any mode but ``global-only``; ``nearest-guarded`` gives ``nearest``'s weights (its guard,
            :func:`guard_transparent`, needs the accumulations).
        block_rgb: ``[K, N, 3]`` block colours; a block whose colour is NaN/inf at a pixel gets weight 0 there.
        global_rgb: ``[N, 3]`` (``global``).
        camera_origin: ``[3]`` or ``[N, 3]`` (``idw``, ``nearest``, ``nearest-idw``).
        block_centres: ``[K, 3]`` (``idw``, ``nearest``, ``nearest-idw``).
        gamma: IDW exponent (``idw``, ``nearest-idw``, ``surface``).
        block_scores: ``[K, N]`` :func:`region_scores` (``surface``).
        blocks_per_ray: ``surface``: the number of best-scoring usable blocks weighted per pixel;
            ``nearest-idw``: the number of usable blocks nearest the camera weighted per pixel.

    Returns:
        Weights summing to one per pixel, or all zero where no block is usable (use the global
        model there). Apply with :func:`fuse_weighted`; :func:`weights_winner` gives the winner.
    """
    parsed = parse_fusion_mode(mode)
    check_block_values(block_rgb, "block_rgb")
    num_blocks, num_pixels = block_rgb.shape[:2]
    usable = torch.isfinite(block_rgb).all(dim=-1)  # [K, N]
    if parsed.kind == "global-only":
        raise ValueError("global-only fusion has no block weights")
    if parsed.kind == "surface":
        if block_scores is None or block_scores.shape != (num_blocks, num_pixels):
            got = None if block_scores is None else list(block_scores.shape)
            raise ValueError(f"surface fusion needs block_scores of shape [{num_blocks}, {num_pixels}], got {got}")
        selected = select_blocks(block_scores, blocks_per_ray or num_blocks, usable.to(block_scores.device))
        return score_weights(block_scores, selected, gamma).to(block_rgb.device)
    if parsed.kind == "global":
        if global_rgb is None:
            raise ValueError("global fusion needs the global model's colour")
        _, winner = fuse_global_guided(block_rgb, global_rgb)
    elif parsed.kind == "block":
        parse_fusion_mode(parsed, num_blocks)
        winner = torch.full((num_pixels,), int(parsed.block_index or 0), dtype=torch.long, device=block_rgb.device)
        winner = torch.where(usable[int(parsed.block_index or 0)], winner, torch.full_like(winner, -1))
    else:
        if camera_origin is None or block_centres is None:
            raise ValueError(f"fusion mode {parsed.kind!r} needs camera_origin and block_centres")
        if block_centres.shape[0] != num_blocks:
            raise ValueError(f"{block_centres.shape[0]} block centres for {num_blocks} block outputs")
        origins = camera_origin if camera_origin.ndim == 2 else camera_origin[None].expand(num_pixels, 3)
        if parsed.kind == "idw":  # shares over the blocks usable at each pixel
            return idw_weights(origins, block_centres, gamma=gamma, valid=usable.to(origins.device)).to(block_rgb.device)
        if parsed.kind == "nearest-idw":  # shares over the blocks_per_ray nearest usable at each pixel
            return nearest_idw_weights(origins, block_centres, num_nearest=blocks_per_ray or num_blocks, gamma=gamma,
                                       valid=usable.to(origins.device)).to(block_rgb.device)
        winner = nearest_block(origins, block_centres, valid=usable.to(origins.device))
    winner = _per_pixel(winner, num_pixels).to(block_rgb.device)
    weights = torch.zeros(num_blocks, num_pixels, dtype=torch.float32, device=block_rgb.device)
    hit = winner >= 0
    weights[winner.clamp(min=0)[hit], torch.nonzero(hit).squeeze(-1)] = 1.0
    return weights
