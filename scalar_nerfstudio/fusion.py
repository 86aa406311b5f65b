"""Final image blending of block renders (SCALAR-NeRF Sec. 3.4).

Pure tensor functions (torch only, any device).  Shapes use ``K`` blocks, ``N`` pixels
(rays) and ``C`` channels.  Colours are linear RGB in [0, 1]; depths are in the world
units of the renders; positions (camera origins, block centres) must be in one and the
same coordinate frame (e.g. both in the dataparser's transformed frame).

Modes (see :func:`parse_fusion_mode`):

* ``"global"``  -- per pixel, the block colour closest (L2) to the coarse global model's
  colour (the paper's global guidance).  Depth and accumulation follow the colour's winner.
* ``"idw"``     -- inverse distance weighting ``w_k ~ d_k^-gamma`` between the camera origin
  and the block centres (Block-NeRF style).
* ``"nearest"`` -- the block whose centre is nearest to the camera origin.
* ``"global-only"`` -- the global model's outputs, no blocks.
* ``"block:<k>"`` -- block ``k`` only (debugging).
"""

from __future__ import annotations

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
    "idw_weights",
    "nearest_block",
    "parse_fusion_mode",
    "select_winner",
]

FusionMode = Literal["global", "idw", "nearest", "global-only"]
FUSION_MODES: tuple[str, ...] = get_args(FusionMode)
#: Output keys fused by :func:`fuse_outputs` (when present in every input).
FUSED_KEYS: tuple[str, ...] = ("rgb", "depth", "accumulation")


class FusionModeError(ValueError):
    """Unknown or malformed fusion mode string."""


@dataclass(frozen=True)
class ParsedFusionMode:
    """A parsed fusion mode: ``kind`` is a :data:`FusionMode` or ``"block"`` with ``block_index``."""

    kind: Literal["global", "idw", "nearest", "global-only", "block"]
    block_index: int | None = None

    def __str__(self) -> str:
        return f"block:{self.block_index}" if self.kind == "block" else self.kind


def parse_fusion_mode(mode: str | ParsedFusionMode, num_blocks: int | None = None) -> ParsedFusionMode:
    """Parse ``"global" | "idw" | "nearest" | "global-only" | "block:<k>"``.

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
    gamma = float(gamma)
    if not (gamma >= 0.0 and gamma != float("inf")):
        raise ValueError(f"gamma must be finite and >= 0, got {gamma}")
    dist = _distances(camera_origin, block_centres)
    valid_mask = _valid_mask(valid, dist.shape, dist.device)
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
    total = raw.sum(dim=0, keepdim=True)
    weights = torch.where(total > 0, raw / torch.where(total > 0, total, torch.ones_like(total)), torch.zeros_like(raw))
    out_dtype = block_centres.dtype if block_centres.is_floating_point() else torch.float32
    return weights.to(out_dtype)


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
) -> dict[str, Tensor]:
    """Fuse block renders into one output dict.

    ``"rgb"`` is required; ``"depth"`` and ``"accumulation"`` are fused when present in
    every block output (and, for ``"global"``, in the global output), always with the same winner (global / nearest / block) or the same
    weights (idw) as the colour.  Values are ``[N, C]`` or image-shaped ``[H, W, C]``
    (a missing trailing channel axis, e.g. depth ``[H, W]``, is accepted).

    Args:
        mode: A :data:`FusionMode` or ``"block:<k>"``.
        block_outputs: K dicts of block renders of the same pixels.
        global_outputs: The coarse global model's renders; required for ``"global"`` and
            ``"global-only"``, used as fallback (pixels without a usable block) otherwise.
        camera_origin: ``[3]`` or per-pixel ``[H, W, 3]`` / ``[N, 3]`` origins (idw/nearest).
        block_centres: ``[K, 3]`` block centres, same frame as ``camera_origin`` (idw/nearest).
        gamma: IDW exponent.

    Returns:
        Fused ``"rgb"`` (+ ``"depth"``, ``"accumulation"``) shaped like the inputs, and
        ``"block_winner"`` (int64, the pixel shape): the chosen block, the largest-weight
        block for idw, ``-1`` for the global fallback and for ``"global-only"``.
    """
    parsed = parse_fusion_mode(mode)
    if parsed.kind in ("global", "global-only") and (global_outputs is None or "rgb" not in global_outputs):
        raise ValueError(f"fusion mode {str(parsed)!r} needs the global model's outputs (with 'rgb')")
    if parsed.kind != "global-only" and not block_outputs:
        raise ValueError(f"fusion mode {str(parsed)!r} needs at least one block output")
    reference = global_outputs["rgb"] if parsed.kind == "global-only" else block_outputs[0]["rgb"]  # type: ignore[index]
    pixel_shape = reference.shape[:-1]
    num_pixels = reference[..., 0].numel()
    keys = _fused_keys([] if parsed.kind == "global-only" else block_outputs, global_outputs)
    if "rgb" not in keys:
        raise ValueError("every block output must contain 'rgb'")
    if parsed.kind == "global" and global_outputs is not None:
        keys = [k for k in keys if k in global_outputs]
    glob = None
    if global_outputs is not None:
        glob = {k: _flatten(global_outputs[k], pixel_shape, k) for k in keys if k in global_outputs}
    if parsed.kind == "global-only":
        fused = dict(glob)  # type: ignore[arg-type]
        winner = torch.full((num_pixels,), -1, dtype=torch.long, device=reference.device)
    else:
        stacked = {k: torch.stack([_flatten(o[k], pixel_shape, k) for o in block_outputs]) for k in keys}
        fused, winner = _fuse_blocks(parsed, stacked, glob, camera_origin, block_centres, gamma, pixel_shape)
    out = {k: v.reshape(*pixel_shape, v.shape[-1]) for k, v in fused.items()}
    out["block_winner"] = winner.reshape(pixel_shape)
    return out


def _fuse_blocks(
    parsed: ParsedFusionMode,
    stacked: dict[str, Tensor],
    glob: dict[str, Tensor] | None,
    camera_origin: Tensor | None,
    block_centres: Tensor | None,
    gamma: float,
    pixel_shape: torch.Size,
) -> tuple[dict[str, Tensor], Tensor]:
    """Fuse stacked ``[K, N, C]`` block values; returns (fused ``[N, C]`` per key, winner ``[N]``)."""
    num_blocks, num_pixels = stacked["rgb"].shape[:2]
    fallback = (lambda k: glob.get(k)) if glob is not None else (lambda k: None)
    if parsed.kind == "global":
        _, winner = fuse_global_guided(stacked["rgb"], glob["rgb"])  # type: ignore[index]
    elif parsed.kind == "block":
        parse_fusion_mode(parsed, num_blocks)
        winner = torch.full((num_pixels,), int(parsed.block_index or 0), dtype=torch.long)
    else:
        if camera_origin is None or block_centres is None:
            raise ValueError(f"fusion mode {parsed.kind!r} needs camera_origin and block_centres")
        if block_centres.shape[0] != num_blocks:
            raise ValueError(f"{block_centres.shape[0]} block centres for {num_blocks} block outputs")
        origins = _origins(camera_origin, pixel_shape)
        if parsed.kind == "idw":
            weights = idw_weights(origins, block_centres, gamma)
            fused = {k: fuse_weighted(v, weights, fallback(k)) for k, v in stacked.items()}
            winner = _per_pixel(torch.argmax(weights, dim=0), num_pixels).to(stacked["rgb"].device)
            return fused, winner
        winner = _per_pixel(nearest_block(origins, block_centres), num_pixels)
    winner = winner.to(stacked["rgb"].device)
    return {k: select_winner(v, winner, fallback(k)) for k, v in stacked.items()}, winner
