"""Applying per-pixel block weights: the weighted sum over blocks, the winner's values, and the
winner of a set of weights (torch only)."""

from __future__ import annotations

import torch
from torch import Tensor

from scalar_nerfstudio.fusion.numerics import check_block_values, compute_dtype


def select_winner(block_values: Tensor, winner: Tensor, fallback: Tensor | None = None) -> Tensor:
    """Gather each pixel's value from its winning block.

    Args:
        block_values: ``[K, N, C]`` per-block values (colour, depth, accumulation, ...).
        winner: ``[N]`` int block index per pixel; ``-1`` means "use ``fallback``".
        fallback: ``[N, C]`` values for pixels with ``winner == -1`` (required if any).

    Returns:
        ``[N, C]`` selected values.
    """
    check_block_values(block_values)
    num_blocks, num_pixels, channels = block_values.shape
    winner = winner.to(device=block_values.device, dtype=torch.long)
    if winner.shape != (num_pixels,):
        raise ValueError(f"winner must have shape [{num_pixels}], got {list(winner.shape)}")
    if winner.numel() and (winner.min() < -1 or winner.max() >= num_blocks):
        raise ValueError(f"winner values must be in [-1, {num_blocks}), got [{int(winner.min())}, {int(winner.max())}]")
    index = winner.clamp(min=0).view(1, num_pixels, 1).expand(1, num_pixels, channels)
    picked = torch.gather(block_values, 0, index)[0]
    missing = winner < 0
    if not bool(missing.any()):
        return picked
    if fallback is None:
        raise ValueError(f"{int(missing.sum())} pixel(s) have winner -1 but no fallback was given")
    if fallback.shape != picked.shape:
        raise ValueError(f"fallback must have shape {list(picked.shape)}, got {list(fallback.shape)}")
    return torch.where(missing[:, None], fallback.to(picked), picked)


def fuse_weighted(block_values: Tensor, weights: Tensor, fallback: Tensor | None = None) -> Tensor:
    """Weighted sum over blocks, ignoring NaN/inf contributions.

    Args:
        block_values: ``[K, N, C]`` per-block values.
        weights: ``[K]`` (same for all pixels) or ``[K, N]`` non-negative weights.
        fallback: Optional ``[N, C]`` values for pixels without any usable contribution.

    Returns:
        ``[N, C]``.  Per pixel, a block whose value is non-finite in any channel is
        dropped and the remaining weights are renormalised.  Pixels with no usable
        contribution (all dropped or zero weight) get ``fallback`` or NaN.
    """
    check_block_values(block_values)
    num_blocks, num_pixels, _ = block_values.shape
    dtype = compute_dtype(block_values, weights)
    weights = weights.to(device=block_values.device, dtype=dtype)
    if weights.shape == (num_blocks,):
        weights = weights[:, None].expand(num_blocks, num_pixels)
    if weights.shape != (num_blocks, num_pixels):
        raise ValueError(f"weights must have shape [{num_blocks}] or [{num_blocks}, {num_pixels}], got {list(weights.shape)}")
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise ValueError("weights must be finite and non-negative")
    usable = torch.isfinite(block_values).all(dim=-1)
    weights = torch.where(usable, weights, torch.zeros_like(weights))
    # Normalised per pixel before the sum: divided by the largest weight, then by the sum (1..K), the
    # weights are a convex combination, so neither huge nor tiny weights over- or underflow.
    largest = weights.amax(dim=0)
    scaled = weights / torch.where(largest > 0, largest, torch.ones_like(largest))
    shares = scaled / scaled.sum(dim=0).clamp_min(1.0)
    values = torch.where(usable[..., None], block_values, torch.zeros_like(block_values)).to(dtype)
    fused = (shares[..., None] * values).sum(dim=0)
    fill = torch.full_like(fused, float("nan")) if fallback is None else fallback.to(fused)
    if fill.shape != fused.shape:
        raise ValueError(f"fallback must have shape {list(fused.shape)}, got {list(fill.shape)}")
    return torch.where((largest > 0)[:, None], fused, fill).to(block_values.dtype)


def weights_winner(weights: Tensor) -> Tensor:
    """``[K, N]`` fusion weights -> ``[N]`` int64 index of the largest weight (lowest on ties), ``-1``
    where every weight is 0 (the pixel falls back to the global model)."""
    winner = torch.argmax(weights, dim=0)
    return torch.where((weights > 0).any(dim=0), winner, torch.full_like(winner, -1))
