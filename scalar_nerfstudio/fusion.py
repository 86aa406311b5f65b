"""Final image blending of block renders (SCALAR-NeRF Sec. 3.4).

Pure tensor functions (torch only, any device).  Shapes use ``K`` blocks, ``N`` pixels
(rays) and ``C`` channels.  Colours are linear RGB in [0, 1]; depths are in the world
units of the renders; positions (camera origins, block centres) must be in one and the
same coordinate frame (e.g. both in the dataparser's transformed frame).

Every mode is a set of per-pixel block weights (:func:`fusion_weights`, one-hot for the winner
modes) applied by :func:`fuse_weighted`. ``global``, ``idw`` and ``surface`` can be restricted per
pixel to a few blocks chosen by :func:`select_blocks` (those whose region holds the global model's
surface point): a block outside a pixel's selection is not rendered there (its values are NaN, which
every rule treats as "not available").

Modes (see :func:`parse_fusion_mode`):

* ``"global"``  -- per pixel, the block colour closest (L2) to the coarse global model's
  colour (the paper's global guidance).  Depth and accumulation follow the colour's winner.
* ``"idw"``     -- inverse distance weighting ``w_k ~ d_k^-gamma`` between the camera origin
  and the block centres (Block-NeRF style).
* ``"nearest"`` -- the block whose centre is nearest to the camera origin.
* ``"nearest-guarded"`` -- ``nearest``, except where that block is transparent and the global model
  opaque (:func:`guard_transparent`): the global model's values there. Guards against a block that
  did not learn what the global model shows (a block that never trained renders the background).
* ``"nearest-idw"`` -- the ``blocks_per_ray`` blocks whose centres are nearest to the camera origin,
  weighted by inverse distance ``d_k^-gamma`` (:func:`nearest_idw_weights`): ``nearest`` blended
  with its neighbours where a camera stands between blocks (two blocks per ray: +0.13-0.16 dB over
  ``nearest`` on the 2 x 2 town, +0.01 dB on the 3 x 3, 0.36 dB below it on castle-P30,
  docs/fusion.md: not the default).
* ``"surface"`` -- the block whose region holds the surface the global model's depth points to:
  per pixel, the point ``o + t d`` at the global depth ``t`` is scored against every block's region
  (:func:`region_scores`, <= 1 inside it), the ``blocks_per_ray`` best are kept and weighted by
  inverse score (one block per ray: that block's colour).
* ``"global-only"`` -- the global model's outputs, no blocks.
* ``"block:<k>"`` -- block ``k`` only (debugging).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import torch
from torch import Tensor

__all__ = [
    "FUSED_KEYS",
    "FUSION_MODES",
    "FusionMode",
    "FusionModeError",
    "ParsedFusionMode",
    "fuse_global_guided",
    "fuse_outputs",
    "fuse_weighted",
    "fusion_weights",
    "guard_transparent",
    "idw_weights",
    "nearest_block",
    "nearest_blocks",
    "nearest_idw_weights",
    "parse_fusion_mode",
    "region_scores",
    "score_weights",
    "select_blocks",
    "select_winner",
    "surface_points",
    "transparent_pixels",
    "weights_winner",
]

FusionMode = Literal["global", "surface", "idw", "nearest", "nearest-guarded", "nearest-idw", "global-only"]
FUSION_MODES: tuple[str, ...] = get_args(FusionMode)
#: Output keys fused by :func:`fuse_outputs` (when present in every input).
FUSED_KEYS: tuple[str, ...] = ("rgb", "depth", "accumulation")


class FusionModeError(ValueError):
    """Unknown or malformed fusion mode string."""


@dataclass(frozen=True)
class ParsedFusionMode:
    """A parsed fusion mode: ``kind`` is a :data:`FusionMode` or ``"block"`` with ``block_index``."""

    kind: Literal["global", "surface", "idw", "nearest", "nearest-guarded", "nearest-idw", "global-only", "block"]
    block_index: int | None = None

    def __str__(self) -> str:
        return f"block:{self.block_index}" if self.kind == "block" else self.kind


def parse_fusion_mode(mode: str | ParsedFusionMode, num_blocks: int | None = None) -> ParsedFusionMode:
    """Parse ``"global" | "surface" | "idw" | "nearest" | "nearest-guarded" | "nearest-idw" | "global-only" | "block:<k>"``.

    Args:
        mode: The mode string (case-insensitive, surrounding blanks ignored) or an already parsed mode.
        num_blocks: If given, ``block:<k>`` must satisfy ``0 <= k < num_blocks``.

    Raises:
        FusionModeError: For an unknown mode or a bad block index.
    """
    if isinstance(mode, ParsedFusionMode):
        parsed = mode
    else:
        text = str(mode).strip().lower()
        if text in FUSION_MODES:
            return ParsedFusionMode(kind=text)  # type: ignore[arg-type]
        if not text.startswith("block:"):
            valid = ", ".join(repr(m) for m in FUSION_MODES)
            raise FusionModeError(f"unknown fusion mode {mode!r}; expected one of {valid} or 'block:<k>'")
        index_text = text.split(":", 1)[1]
        if not index_text.isdigit():
            raise FusionModeError(f"bad fusion mode {mode!r}: 'block:<k>' needs a non-negative integer k")
        parsed = ParsedFusionMode(kind="block", block_index=int(index_text))
    if parsed.kind == "block" and num_blocks is not None and not 0 <= (parsed.block_index or 0) < num_blocks:
        raise FusionModeError(f"fusion mode {str(parsed)!r}: block index out of range, there are {num_blocks} blocks")
    return parsed


# --------------------------------------------------------------------------- helpers


def _check_block_values(block_values: Tensor, name: str = "block_values") -> None:
    """Require a ``[K, N, C]`` tensor with ``K >= 1``."""
    if block_values.ndim != 3 or block_values.shape[0] < 1:
        raise ValueError(f"{name} must have shape [K, N, C] with K >= 1, got {list(block_values.shape)}")


def _usable(block_values: Tensor, valid: Tensor | None) -> Tensor:
    """``[K, N]`` bool: block output finite in every channel and (if given) marked valid."""
    usable = torch.isfinite(block_values).all(dim=-1)
    if valid is not None:
        if valid.shape != usable.shape:
            raise ValueError(f"valid must have shape {list(usable.shape)}, got {list(valid.shape)}")
        usable = usable & valid.to(device=usable.device, dtype=torch.bool)
    return usable


# --------------------------------------------------------------------------- global guidance


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
    _check_block_values(block_rgb, "block_rgb")
    if global_rgb.shape != block_rgb.shape[1:]:
        raise ValueError(f"global_rgb must have shape {list(block_rgb.shape[1:])}, got {list(global_rgb.shape)}")
    usable = _usable(block_rgb, valid)
    diff = torch.where(usable[..., None], block_rgb - global_rgb[None], torch.zeros_like(block_rgb))
    dist = (diff * diff).sum(dim=-1)
    dist = torch.where(torch.isfinite(global_rgb).all(dim=-1)[None], dist, torch.zeros_like(dist))
    dist = torch.where(usable & torch.isfinite(dist), dist, torch.full_like(dist, float("inf")))
    winner = torch.argmin(dist, dim=0)  # first minimum -> lowest index on ties
    winner = torch.where(torch.isfinite(dist).any(dim=0), winner, torch.full_like(winner, -1))
    return select_winner(block_rgb, winner, fallback=global_rgb), winner


def select_winner(block_values: Tensor, winner: Tensor, fallback: Tensor | None = None) -> Tensor:
    """Gather each pixel's value from its winning block.

    Args:
        block_values: ``[K, N, C]`` per-block values (colour, depth, accumulation, ...).
        winner: ``[N]`` int block index per pixel; ``-1`` means "use ``fallback``".
        fallback: ``[N, C]`` values for pixels with ``winner == -1`` (required if any).

    Returns:
        ``[N, C]`` selected values.
    """
    _check_block_values(block_values)
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


# --------------------------------------------------------------------------- distance based


def _compute_dtype(*tensors: Tensor) -> torch.dtype:
    """The dtype fusion computes in: the inputs' common floating dtype, at least float32.

    Never promoted further: float32 inputs are computed in float32 (float64 is slow on consumer GPUs
    and unsupported on MPS); the formulations below are what keeps float32 safe.
    """
    dtype = torch.float32
    for tensor in tensors:
        if tensor.is_floating_point():
            dtype = torch.promote_types(dtype, tensor.dtype)
    return dtype


def _norm(vectors: Tensor) -> Tensor:
    """Euclidean norm over the last axis without overflow or underflow: ``m * ||v / m||`` with ``m = max |v_i|``
    (squaring 1e-25 or 1e20 directly gives 0 or inf in float32)."""
    scale = vectors.abs().amax(dim=-1, keepdim=True)
    unit = vectors / torch.where(scale > 0, scale, torch.ones_like(scale))
    return scale.squeeze(-1) * torch.linalg.vector_norm(unit, dim=-1)


def _distances(camera_origin: Tensor, block_centres: Tensor) -> Tensor:
    """Euclidean distances: ``[K]`` for an origin ``[3]``, ``[K, N]`` for origins ``[N, 3]``."""
    if block_centres.ndim != 2 or block_centres.shape[1] != 3 or block_centres.shape[0] < 1:
        raise ValueError(f"block_centres must have shape [K, 3] with K >= 1, got {list(block_centres.shape)}")
    dtype = _compute_dtype(camera_origin, block_centres)
    origin = camera_origin.to(device=block_centres.device, dtype=dtype)
    centres = block_centres.to(dtype)
    if not (bool(torch.isfinite(origin).all()) and bool(torch.isfinite(centres).all())):
        raise ValueError("camera_origin and block_centres must be finite (found NaN/inf)")
    if origin.shape == (3,):
        return _norm(centres - origin)
    if origin.ndim == 2 and origin.shape[1] == 3:
        return _norm(centres[:, None, :] - origin[None])
    raise ValueError(f"camera_origin must have shape [3] or [N, 3], got {list(camera_origin.shape)}")


def _valid_mask(valid: Tensor | None, shape: torch.Size, device: torch.device) -> Tensor:
    """Broadcast an optional ``[K]`` or ``[K, N]`` validity mask to ``shape``."""
    if valid is None:
        return torch.ones(shape, dtype=torch.bool, device=device)
    valid = valid.to(device=device, dtype=torch.bool)
    if valid.shape == shape:
        return valid
    if valid.ndim == 1 and len(shape) == 2 and valid.shape[0] == shape[0]:
        return valid[:, None].expand(shape)
    raise ValueError(f"valid must have shape [K] or {list(shape)}, got {list(valid.shape)}")


def idw_weights(
    camera_origin: Tensor, block_centres: Tensor, gamma: float = 1.0, valid: Tensor | None = None
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
    return nearest_idw_weights(camera_origin, block_centres, None, gamma, valid)


def _check_gamma(gamma: float) -> float:
    gamma = float(gamma)
    if not (gamma >= 0.0 and gamma != float("inf")):
        raise ValueError(f"gamma must be finite and >= 0, got {gamma}")
    return gamma


def _inverse_distance_shares(dist: Tensor, valid_mask: Tensor, gamma: float) -> Tensor:
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


# --------------------------------------------------------------------------- surface-guided selection


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
    dtype = _compute_dtype(points, centres, radii)
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
    mask = _valid_mask(usable, scores.shape, scores.device)
    ranked = torch.where(mask, torch.nan_to_num(scores, nan=float("inf")), torch.full_like(scores, float("inf")))
    if blocks_per_ray >= scores.shape[0]:
        return mask.clone()
    order = torch.sort(ranked, dim=0, stable=True).indices[:blocks_per_ray]  # [M, N]
    selected = torch.zeros_like(mask)
    selected.scatter_(0, order, torch.ones_like(order, dtype=torch.bool))
    return selected & mask


def score_weights(scores: Tensor, selected: Tensor, gamma: float = 1.0) -> Tensor:
    """``[K, N]`` weights of the ``surface`` rule: ``score^-gamma`` over the selected blocks, summing to one.

    A score of 0 (the point at a block's centre) takes all the weight; pixels with nothing selected
    get all-zero weights (the caller's fallback).
    """
    return _inverse_distance_shares(torch.nan_to_num(scores, nan=float("inf")), selected, _check_gamma(gamma))


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
    dist = _distances(camera_origin, block_centres)
    valid_mask = _valid_mask(valid, dist.shape, dist.device)
    dist = torch.where(valid_mask, dist, torch.full_like(dist, float("inf")))
    index = torch.argmin(dist, dim=0)
    return torch.where(valid_mask.any(dim=0), index, torch.full_like(index, -1))


def nearest_blocks(camera_origin: Tensor, block_centres: Tensor, num_nearest: int | None, valid: Tensor | None = None) -> Tensor:
    """``[K]`` or ``[K, N]`` bool: the ``num_nearest`` valid blocks whose centres are nearest the camera.

    Args:
        camera_origin: ``[3]`` (one camera) or ``[N, 3]`` (per ray) positions.
        block_centres: ``[K, 3]`` block centres, same frame and units as the origin.
        num_nearest: how many blocks (>= 1); with ``>= K`` or None every valid block.
        valid: optional ``[K]`` or ``[K, N]`` bool; invalid blocks are never chosen.

    Ties in distance go to the lower block index; nothing is chosen where no block is valid.
    """
    return _nearest_of(_distances(camera_origin, block_centres), num_nearest, valid)


def _nearest_of(dist: Tensor, num_nearest: int | None, valid: Tensor | None) -> Tensor:
    """:func:`nearest_blocks` from the ``[K]`` or ``[K, N]`` distances."""
    valid_mask = _valid_mask(valid, dist.shape, dist.device)
    if num_nearest is None:
        return valid_mask
    if num_nearest < 1:
        raise ValueError(f"num_nearest must be >= 1, got {num_nearest}")
    flat = (dist.shape[0], -1)
    return select_blocks(dist.reshape(flat), num_nearest, valid_mask.reshape(flat)).reshape(dist.shape)


def nearest_idw_weights(
    camera_origin: Tensor, block_centres: Tensor, num_nearest: int | None, gamma: float = 2.0, valid: Tensor | None = None
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
    gamma = _check_gamma(gamma)
    dist = _distances(camera_origin, block_centres)
    weights = _inverse_distance_shares(dist, _nearest_of(dist, num_nearest, valid), gamma)
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
    weights: Tensor, block_accumulation: Tensor, global_accumulation: Tensor, threshold: float = 0.5
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
    _check_block_values(block_values)
    num_blocks, num_pixels, _ = block_values.shape
    dtype = _compute_dtype(block_values, weights)
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


# --------------------------------------------------------------------------- outputs


def _flatten(value: Tensor, pixel_shape: torch.Size, key: str) -> Tensor:
    """``[*pixel_shape, C]`` (or ``[*pixel_shape]``) -> ``[N, C]``."""
    if value.shape == pixel_shape:
        value = value[..., None]
    if value.shape[:-1] != pixel_shape:
        raise ValueError(f"output {key!r} has shape {list(value.shape)}, expected [{', '.join(map(str, pixel_shape))}, C]")
    return value.reshape(-1, value.shape[-1])


def _fused_keys(block_outputs: Sequence[Mapping[str, Tensor]], global_outputs: Mapping[str, Tensor] | None) -> list[str]:
    """The :data:`FUSED_KEYS` present in every block output (or, with no blocks, in the global one)."""
    sources = list(block_outputs) if block_outputs else ([global_outputs] if global_outputs is not None else [])
    return [k for k in FUSED_KEYS if sources and all(k in s for s in sources)]


def _origins(camera_origin: Tensor, pixel_shape: torch.Size) -> Tensor:
    """One ``[3]`` origin, or per-pixel origins ``[*pixel_shape, 3]`` flattened to ``[N, 3]``."""
    if camera_origin.shape == (3,):
        return camera_origin
    if camera_origin.shape == (*pixel_shape, 3):
        return camera_origin.reshape(-1, 3)
    raise ValueError(f"camera_origin must have shape [3] or [{', '.join(map(str, pixel_shape))}, 3], got {list(camera_origin.shape)}")


def _per_pixel(index: Tensor, num_pixels: int) -> Tensor:
    """Broadcast a scalar or ``[N]`` block index to ``[N]`` int64."""
    return index.to(torch.long).reshape(-1).expand(num_pixels) if index.numel() == 1 else index.to(torch.long)


def fuse_outputs(
    mode: str | ParsedFusionMode,
    block_outputs: Sequence[Mapping[str, Tensor]],
    global_outputs: Mapping[str, Tensor] | None,
    camera_origin: Tensor | None,
    block_centres: Tensor | None,
    gamma: float = 1.0,
    block_scores: Tensor | None = None,
    blocks_per_ray: int | None = None,
    guard_accumulation: float = 0.5,
) -> dict[str, Tensor]:
    """Fuse block renders into one output dict.

    ``"rgb"`` is required; ``"depth"`` and ``"accumulation"`` are fused when present in
    every block output (and, for ``"global"``, in the global output), always with the same weights
    as the colour (:func:`fusion_weights`). Values are ``[N, C]`` or image-shaped ``[H, W, C]``
    (a missing trailing channel axis, e.g. depth ``[H, W]``, is accepted). A block value that is
    NaN/inf at a pixel (e.g. the block was not rendered there) is not used at that pixel.

    Args:
        mode: A :data:`FusionMode` or ``"block:<k>"``.
        block_outputs: K dicts of block renders of the same pixels.
        global_outputs: The coarse global model's renders; required for ``"global"``,
            ``"global-only"`` and ``"nearest-guarded"`` (with ``"accumulation"``), used as fallback
            (pixels without a usable block) otherwise.
        camera_origin: ``[3]`` or per-pixel ``[H, W, 3]`` / ``[N, 3]`` origins (idw/nearest/nearest-idw).
        block_centres: ``[K, 3]`` block centres, same frame as ``camera_origin`` (idw/nearest/nearest-idw).
        gamma: IDW exponent (``idw``, ``nearest-idw`` and ``surface``).
        block_scores: ``[K, *pixel_shape]`` or ``[K, N]`` :func:`region_scores` of each pixel's
            surface point (required for ``surface``).
        blocks_per_ray: ``surface``: how many of the best-scoring blocks are weighted per pixel;
            ``nearest-idw``: how many of the blocks nearest the camera (default: all).
        guard_accumulation: ``nearest-guarded``: the accumulation below which a block counts as
            transparent and at or above which the global model counts as opaque (:func:`guard_transparent`).

    Returns:
        Fused ``"rgb"`` (+ ``"depth"``, ``"accumulation"``) shaped like the inputs, and
        ``"block_winner"`` (int64, the pixel shape): the chosen block, the largest-weight
        block for idw / nearest-idw / surface, ``-1`` for the global fallback and for ``"global-only"``.
    """
    parsed = parse_fusion_mode(mode)
    if parsed.kind in ("global", "global-only", "nearest-guarded") and (global_outputs is None or "rgb" not in global_outputs):
        raise ValueError(f"fusion mode {str(parsed)!r} needs the global model's outputs (with 'rgb')")
    if parsed.kind != "global-only" and not block_outputs:
        raise ValueError(f"fusion mode {str(parsed)!r} needs at least one block output")
    reference = global_outputs["rgb"] if parsed.kind == "global-only" else block_outputs[0]["rgb"]  # type: ignore[index]
    pixel_shape = reference.shape[:-1]
    num_pixels = reference[..., 0].numel()
    keys = _fused_keys([] if parsed.kind == "global-only" else block_outputs, global_outputs)
    if "rgb" not in keys:
        raise ValueError("every block output must contain 'rgb'")
    if parsed.kind in ("global", "nearest-guarded") and global_outputs is not None:
        keys = [k for k in keys if k in global_outputs]
    glob = None
    if global_outputs is not None:
        glob = {k: _flatten(global_outputs[k], pixel_shape, k) for k in keys if k in global_outputs}
    if parsed.kind == "global-only":
        out = {k: v.reshape(*pixel_shape, v.shape[-1]) for k, v in glob.items()}  # type: ignore[union-attr]
        out["block_winner"] = torch.full(pixel_shape, -1, dtype=torch.long, device=reference.device)
        return out
    stacked = {k: torch.stack([_flatten(o[k], pixel_shape, k) for o in block_outputs]) for k in keys}
    scores = None if block_scores is None else block_scores.reshape(len(block_outputs), num_pixels)
    weights = fusion_weights(
        parsed, stacked["rgb"], None if glob is None else glob.get("rgb"),
        None if camera_origin is None else _origins(camera_origin, pixel_shape), block_centres, gamma, scores, blocks_per_ray,
    )
    if parsed.kind == "nearest-guarded":
        if "accumulation" not in stacked:
            raise ValueError("fusion mode 'nearest-guarded' needs 'accumulation' in every block output and in the global model's")
        weights = guard_transparent(weights, stacked["accumulation"], glob["accumulation"], guard_accumulation)  # type: ignore[index]
    fused = {k: fuse_weighted(v, weights, None if glob is None else glob.get(k)) for k, v in stacked.items()}
    out = {k: v.reshape(*pixel_shape, v.shape[-1]) for k, v in fused.items()}
    out["block_winner"] = weights_winner(weights).reshape(pixel_shape)
    return out


def weights_winner(weights: Tensor) -> Tensor:
    """``[K, N]`` fusion weights -> ``[N]`` int64 index of the largest weight (lowest on ties), ``-1``
    where every weight is 0 (the pixel falls back to the global model)."""
    winner = torch.argmax(weights, dim=0)
    return torch.where((weights > 0).any(dim=0), winner, torch.full_like(winner, -1))


def fusion_weights(
    mode: str | ParsedFusionMode,
    block_rgb: Tensor,
    global_rgb: Tensor | None = None,
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
    _check_block_values(block_rgb, "block_rgb")
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
            return idw_weights(origins, block_centres, gamma, valid=usable.to(origins.device)).to(block_rgb.device)
        if parsed.kind == "nearest-idw":  # shares over the blocks_per_ray nearest usable at each pixel
            return nearest_idw_weights(origins, block_centres, blocks_per_ray or num_blocks, gamma,
                                       valid=usable.to(origins.device)).to(block_rgb.device)
        winner = nearest_block(origins, block_centres, valid=usable.to(origins.device))
    winner = _per_pixel(winner, num_pixels).to(block_rgb.device)
    weights = torch.zeros(num_blocks, num_pixels, dtype=torch.float32, device=block_rgb.device)
    hit = winner >= 0
    weights[winner.clamp(min=0)[hit], torch.nonzero(hit).squeeze(-1)] = 1.0
    return weights
