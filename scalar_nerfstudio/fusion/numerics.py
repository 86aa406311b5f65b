"""Checks and numerics shared by the fusion rules (package-internal; torch only).

Distances and inverse-distance shares are computed so that float32 stays safe for tiny or huge
coordinates and exponents: norms are scaled by the largest component, and weights are taken as ratios
to the largest one before any power or sum.
"""

from __future__ import annotations

import torch
from torch import Tensor


def check_block_values(block_values: Tensor, name: str = "block_values") -> None:
    """Require a ``[K, N, C]`` tensor with ``K >= 1``."""
    if block_values.ndim != 3 or block_values.shape[0] < 1:
        raise ValueError(f"{name} must have shape [K, N, C] with K >= 1, got {list(block_values.shape)}")


def usable_mask(block_values: Tensor, valid: Tensor | None) -> Tensor:
    """``[K, N]`` bool: block output finite in every channel and (if given) marked valid."""
    usable = torch.isfinite(block_values).all(dim=-1)
    if valid is not None:
        if valid.shape != usable.shape:
            raise ValueError(f"valid must have shape {list(usable.shape)}, got {list(valid.shape)}")
        usable = usable & valid.to(device=usable.device, dtype=torch.bool)
    return usable


def compute_dtype(*tensors: Tensor) -> torch.dtype:
    """The dtype fusion computes in: the inputs' common floating dtype, at least float32.

    Never promoted further: float32 inputs are computed in float32 (float64 is slow on consumer GPUs
    and unsupported on MPS); the formulations below are what keeps float32 safe.
    """
    dtype = torch.float32
    for tensor in tensors:
        if tensor.is_floating_point():
            dtype = torch.promote_types(dtype, tensor.dtype)
    return dtype


def stable_norm(vectors: Tensor) -> Tensor:
    """Euclidean norm over the last axis without overflow or underflow: ``m * ||v / m||`` with ``m = max |v_i|``
    (squaring 1e-25 or 1e20 directly gives 0 or inf in float32)."""
    scale = vectors.abs().amax(dim=-1, keepdim=True)
    unit = vectors / torch.where(scale > 0, scale, torch.ones_like(scale))
    return scale.squeeze(-1) * torch.linalg.vector_norm(unit, dim=-1)


def distances(camera_origin: Tensor, block_centres: Tensor) -> Tensor:
    """Euclidean distances: ``[K]`` for an origin ``[3]``, ``[K, N]`` for origins ``[N, 3]``."""
    if block_centres.ndim != 2 or block_centres.shape[1] != 3 or block_centres.shape[0] < 1:
        raise ValueError(f"block_centres must have shape [K, 3] with K >= 1, got {list(block_centres.shape)}")
    dtype = compute_dtype(camera_origin, block_centres)
    origin = camera_origin.to(device=block_centres.device, dtype=dtype)
    centres = block_centres.to(dtype)
    if not (bool(torch.isfinite(origin).all()) and bool(torch.isfinite(centres).all())):
        raise ValueError("camera_origin and block_centres must be finite (found NaN/inf)")
    if origin.shape == (3,):
        return stable_norm(centres - origin)
    if origin.ndim == 2 and origin.shape[1] == 3:
        return stable_norm(centres[:, None, :] - origin[None])
    raise ValueError(f"camera_origin must have shape [3] or [N, 3], got {list(camera_origin.shape)}")


def broadcast_valid(valid: Tensor | None, shape: torch.Size, device: torch.device) -> Tensor:
    """Broadcast an optional ``[K]`` or ``[K, N]`` validity mask to ``shape``."""
    if valid is None:
        return torch.ones(shape, dtype=torch.bool, device=device)
    valid = valid.to(device=device, dtype=torch.bool)
    if valid.shape == shape:
        return valid
    if valid.ndim == 1 and len(shape) == 2 and valid.shape[0] == shape[0]:
        return valid[:, None].expand(shape)
    raise ValueError(f"valid must have shape [K] or {list(shape)}, got {list(valid.shape)}")


def check_gamma(gamma: float) -> float:
    gamma = float(gamma)
    if not (gamma >= 0.0 and gamma != float("inf")):
        raise ValueError(f"gamma must be finite and >= 0, got {gamma}")
    return gamma


def inverse_distance_shares(dist: Tensor, valid_mask: Tensor, gamma: float) -> Tensor:
    """``[K]`` or ``[K, N]`` non-negative distances -> ``d_k^-gamma`` shares summing to one over the valid
    ``k`` (0 where none is valid); a distance of 0 takes all the weight (shared among equal zeros)."""
    if gamma == 0.0:
        raw = valid_mask.to(dist.dtype)
    else:
        # w_k / w_max = (d_min / d_k)^gamma = exp(-gamma log(d_k / d_min)): the ratio is taken before the
        # log, so its rounding (not that of log d, ~|log d| eps) is what gamma multiplies, and nothing
        # overflows or underflows for tiny or huge distances or a large gamma (a ratio of inf gives 0).
        far = torch.full_like(dist, float("inf"))
        nearest = torch.where(valid_mask, dist, far).amin(dim=0, keepdim=True)
        ratio = dist / torch.where(nearest > 0, nearest, torch.ones_like(nearest))  # >= 1 where valid, but at a centre (below)
        raw = torch.where(valid_mask, torch.exp(-gamma * torch.log(ratio)), torch.zeros_like(dist))
        at_centre = (dist == 0) & valid_mask
        raw = torch.where(at_centre.any(dim=0, keepdim=True), at_centre.to(raw), raw)
    raw = torch.nan_to_num(raw, nan=0.0)
    total = raw.sum(dim=0, keepdim=True)
    return torch.where(total > 0, raw / torch.where(total > 0, total, torch.ones_like(total)), torch.zeros_like(raw))
