"""Fusing whole output dicts of block renders (``rgb``, ``depth``, ``accumulation``) in one call:
what offline evaluation and the tests use (torch only)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from scalar_nerfstudio.fusion.blend import fuse_weighted, weights_winner
from scalar_nerfstudio.fusion.modes import ParsedFusionMode, parse_fusion_mode
from scalar_nerfstudio.fusion.rules import fusion_weights, guard_transparent

#: Output keys fused by :func:`fuse_outputs` (when present in every input).
FUSED_KEYS: tuple[str, ...] = ("rgb", "depth", "accumulation")


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


def fuse_outputs(
    mode: str | ParsedFusionMode,
    block_outputs: Sequence[Mapping[str, Tensor]],
    global_outputs: Mapping[str, Tensor] | None,
    *,
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
        camera_origin=None if camera_origin is None else _origins(camera_origin, pixel_shape), block_centres=block_centres, gamma=gamma,
        block_scores=scores, blocks_per_ray=blocks_per_ray,
    )
    if parsed.kind == "nearest-guarded":
        if "accumulation" not in stacked:
            raise ValueError("fusion mode 'nearest-guarded' needs 'accumulation' in every block output and in the global model's")
        weights = guard_transparent(weights, stacked["accumulation"], glob["accumulation"],  # type: ignore[index]
                                    threshold=guard_accumulation)
    fused = {k: fuse_weighted(v, weights, None if glob is None else glob.get(k)) for k, v in stacked.items()}
    out = {k: v.reshape(*pixel_shape, v.shape[-1]) for k, v in fused.items()}
    out["block_winner"] = weights_winner(weights).reshape(pixel_shape)
    return out
