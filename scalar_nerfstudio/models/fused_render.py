"""Fused rendering: a ray batch rendered by the global model and the blocks chosen per ray, fused per pixel.

:class:`FusedRenderer` renders each block only on the rays it is selected for
(:func:`~scalar_nerfstudio.models.block_selection.select_rays`); the fusion sees NaN where a block
was not rendered, which every rule treats as "not available" (``scalar_nerfstudio.fusion``). It is
built per render by :class:`~scalar_nerfstudio.models.scene_model.ScalarSceneModel` from its models,
its block regions and its config as they are at that moment.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Dict, List, Literal, Optional, Set, Tuple, Union

import torch
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor

from scalar_nerfstudio.blocks.palette import BLOCK_PALETTE, GLOBAL_COLOUR
from scalar_nerfstudio.fusion import (
    FUSED_KEYS,
    ParsedFusionMode,
    fuse_weighted,
    fusion_weights,
    guard_transparent,
    transparent_pixels,
    weights_winner,
)
from scalar_nerfstudio.model_components.rendering import (
    facing_normals,
    normals_from_unit_interval,
    normals_to_unit_interval,
    safe_normalise,
)
from scalar_nerfstudio.models.block_selection import BlockRegions, select_rays
from scalar_nerfstudio.models.scalar_model import ScalarModel


@dataclass(frozen=True)
class FusionSettings:
    """The options of fused rendering (see ``ScalarSceneModelConfig`` for each)."""

    blocks_per_ray: int
    idw_gamma: float
    nearest_idw_gamma: float
    guard_accumulation: float
    selection_depth: Literal["field", "grid"]
    observed_blocks_only: bool


def winner_colours(winner: Tensor) -> Tensor:
    """[R, 1] block indices (-1: global) -> [R, 3] viewer colours."""
    palette = torch.tensor([GLOBAL_COLOUR, *BLOCK_PALETTE.tolist()], dtype=torch.float32, device=winner.device)
    index = winner.reshape(-1).long()
    return palette[torch.where(index < 0, 0, 1 + index % len(BLOCK_PALETTE))]


class FusedRenderer:
    """Renders ray batches through the global model and the blocks, fused per pixel.

    Args:
        global_model: the global model.
        block_model: block id -> its model with its weights in memory (loaded if need be).
        block_shell: block id -> its model as held (weights possibly released; for rays it renders none of).
        settings: the fusion options.
        regions: every block's region (indexed by block id); its ``observation`` is used only with
            ``settings.observed_blocks_only``.
        rendered_models: set the models rendered are added to (block ids, ``"global"``).
        rays_rendered_by_block: dict each block's count of rendered rays is added to.
    """

    def __init__(
        self,
        global_model: ScalarModel,
        *,
        block_model: Callable[[int], ScalarModel],
        block_shell: Callable[[int], ScalarModel],
        settings: FusionSettings,
        regions: BlockRegions,
        rendered_models: Set[Union[int, str]],
        rays_rendered_by_block: Dict[int, int],
    ) -> None:
        self.global_model = global_model
        self.block_model = block_model
        self.block_shell = block_shell
        self.settings = settings
        self.regions = regions
        self.rendered_models = rendered_models
        self.rays_rendered_by_block = rays_rendered_by_block

    def render(self, ray_bundle: RayBundle, mode: ParsedFusionMode, block_ids: List[int], *, normals: bool) -> Dict[str, Tensor]:
        """Fused ``rgb`` [R, 3], ``depth`` [R, 1], ``accumulation`` [R, 1], ``block_winner`` [R, 1],
        ``block_colour`` [R, 3]; ``normals`` [R, 3] in [0, 1] when ``normals``.

        ``block_ids`` are the blocks that may render (the started ones ``mode`` uses). The global
        model renders colour for ``global`` / ``global-only`` (and the rays no block could give), its
        depth alone where only the selection needs it. ``block_winner`` is the index of the block that
        gave the pixel (-1: the global model); ``block_colour`` shows it in the block's viewer colour.
        """
        settings = self.settings
        if mode.kind == "global" and settings.blocks_per_ray == 1:
            # One block chosen per ray: it is the closest to the global colour by itself, so the global
            # colour is not rendered (the same image as "surface" with one block per ray).
            mode = ParsedFusionMode(kind="surface")
        origins = ray_bundle.origins.reshape(-1, 3)
        global_outputs: Optional[Dict[str, Tensor]] = None
        if mode.kind in ("global", "global-only") or not block_ids:
            # Its normals only where it is the output (with blocks, "global" takes every pixel from a block).
            global_outputs = self.global_model.render_rays(ray_bundle, normals=normals and not block_ids)
            self.rendered_models.add("global")
        if block_ids:
            selected, scores = self.select_rays(mode, block_ids, ray_bundle, global_outputs=global_outputs)  # [K', R]
            used = selected.any(dim=1)  # blocks no ray chose take no part at all: the cost is O(chosen), not O(K)
            if not bool(used.all()):
                rows = torch.nonzero(used).squeeze(-1)
                block_ids = [block_ids[i] for i in rows.tolist()]
                selected = selected[rows]
                scores = None if scores is None else scores[rows]
        if not block_ids:  # no block, or none chosen by any ray: the global model's render
            if global_outputs is None or (normals and "normals" not in global_outputs):
                global_outputs = self.global_model.render_rays(ray_bundle, normals=normals)
                self.rendered_models.add("global")
            winner = torch.full_like(global_outputs["accumulation"], -1.0)
            return {**global_outputs, "block_winner": winner, "block_colour": winner_colours(winner)}
        block_outputs = [self._render_block_rays(b, ray_bundle, selected[i], normals) for i, b in enumerate(block_ids)]
        self.rendered_models.update(b for i, b in enumerate(block_ids) if bool(selected[i].any()))
        rgb_stack = torch.stack([o["rgb"] for o in block_outputs])  # [K', R, 3]
        weights = fusion_weights(
            ParsedFusionMode(kind="block", block_index=0) if mode.kind == "block" else mode,
            rgb_stack, None if global_outputs is None else global_outputs["rgb"], camera_origin=origins,
            block_centres=self.regions.centres[block_ids].to(origins.device),
            gamma=settings.nearest_idw_gamma if mode.kind == "nearest-idw" else settings.idw_gamma, block_scores=scores,
            blocks_per_ray=settings.blocks_per_ray or None,
        )
        if mode.kind == "nearest-guarded":
            weights, global_outputs = self._guard_transparent_blocks(weights, block_outputs, ray_bundle, normals)
        orphans = ~(weights > 0).any(dim=0)  # [R] rays no block could give: the global model's
        if bool(orphans.any()) and global_outputs is None:
            global_outputs = self._render_global_rays(ray_bundle, orphans, normals)
            self.rendered_models.add("global")
        fused = {
            key: fuse_weighted(torch.stack([o[key] for o in block_outputs]), weights,
                               None if global_outputs is None or key not in global_outputs else global_outputs[key])
            for key in FUSED_KEYS
        }
        if normals:
            fallback = (global_outputs["normals"] if global_outputs is not None and "normals" in global_outputs
                        else normals_to_unit_interval(facing_normals(ray_bundle.directions.reshape(-1, 3))))
            stacked = torch.stack([o["normals"] for o in block_outputs])  # [K', R, 3] in [0, 1]
            if mode.kind in ("global", "nearest", "nearest-guarded", "block"):  # one winner per ray: its normal, bit for bit
                fused["normals"] = fuse_weighted(stacked, weights, fallback)
            else:  # a weighted mix of unit normals, normalised again
                mixed = fuse_weighted(normals_from_unit_interval(stacked), weights, normals_from_unit_interval(fallback))
                fused["normals"] = normals_to_unit_interval(safe_normalise(mixed, normals_from_unit_interval(fallback)))
        position_to_id = torch.tensor([-1, *block_ids], dtype=torch.float32, device=origins.device)
        fused["block_winner"] = position_to_id[weights_winner(weights) + 1][:, None]
        fused["block_colour"] = winner_colours(fused["block_winner"])
        return fused

    @torch.no_grad()
    def select_rays(
        self, mode: ParsedFusionMode, block_ids: List[int], ray_bundle: RayBundle, *, global_outputs: Optional[Dict[str, Tensor]] = None
    ) -> Tuple[Tensor, Optional[Tensor]]:
        """:func:`~scalar_nerfstudio.models.block_selection.select_rays` of the bundle's rays; the global
        depth is taken from ``global_outputs`` when given, else rendered from the density alone."""

        def global_depth() -> Tensor:
            outputs = global_outputs
            if outputs is None:
                outputs = self.global_model.render_depth_only(ray_bundle, source=self.settings.selection_depth)
                self.rendered_models.add("global")
            return outputs["depth"]

        return select_rays(
            mode, block_ids, origins=ray_bundle.origins.reshape(-1, 3), directions=ray_bundle.directions.reshape(-1, 3),
            regions=self.regions if self.settings.observed_blocks_only else replace(self.regions, observation=None),
            blocks_per_ray=self.settings.blocks_per_ray, global_depth=global_depth,
        )

    def _guard_transparent_blocks(
        self, weights: Tensor, block_outputs: List[Dict[str, Tensor]], ray_bundle: RayBundle, normals: bool
    ) -> Tuple[Tensor, Dict[str, Tensor]]:
        """``nearest-guarded``: the global model renders the rays whose block is transparent (and those
        no block gave); where it is opaque, the ray takes its render (:func:`guard_transparent`).

        Returns the ``[K', R]`` weights, zero on the guarded rays, and the global model's outputs (NaN
        on the rays it did not render)."""
        threshold = self.settings.guard_accumulation
        block_accumulation = torch.stack([o["accumulation"] for o in block_outputs])  # [K', R, 1]
        suspects = transparent_pixels(weights, block_accumulation, threshold)  # [R]
        global_outputs = self._render_global_rays(ray_bundle, suspects, normals)
        if bool(suspects.any()):
            self.rendered_models.add("global")
        return guard_transparent(weights, block_accumulation, global_outputs["accumulation"], threshold=threshold), global_outputs

    def _render_block_rays(self, block: int, ray_bundle: RayBundle, rays: Tensor, normals: bool) -> Dict[str, Tensor]:
        """Block ``block``'s render of the rays where ``rays`` [R] is True; NaN on the others."""
        if not bool(rays.any()):
            return self._render_subset(self.block_shell(block), ray_bundle, rays, normals, block)  # NaN, no weights needed
        return self._render_subset(self.block_model(block), ray_bundle, rays, normals, block)

    def _render_global_rays(self, ray_bundle: RayBundle, rays: Tensor, normals: bool) -> Dict[str, Tensor]:
        """The global model's render of the rays where ``rays`` [R] is True; NaN on the others."""
        return self._render_subset(self.global_model, ray_bundle, rays, normals, None)

    def _render_subset(self, model: ScalarModel, ray_bundle: RayBundle, rays: Tensor, normals: bool, block: Optional[int]) -> Dict[str, Tensor]:
        """``model``'s :data:`FUSED_KEYS` (and ``normals``) of the rays where ``rays`` [R] is True, [R, C]
        with NaN on the others; counted in :attr:`rays_rendered_by_block` when ``block`` is given."""
        num_rays = rays.shape[0]
        keys = [*FUSED_KEYS, *(["normals"] if normals else [])]
        widths = {"rgb": 3, "normals": 3}
        device = ray_bundle.origins.device
        count = int(rays.sum())
        if block is not None:
            self.rays_rendered_by_block[block] = self.rays_rendered_by_block.get(block, 0) + count
        if count == num_rays > 0:  # every ray: no NaN-filled copy
            outputs = model.render_rays(ray_bundle.reshape((num_rays,)), normals=normals)
            return {k: outputs[k].reshape(num_rays, -1) for k in keys}
        full = {k: torch.full((num_rays, widths.get(k, 1)), float("nan"), device=device) for k in keys}
        if count == 0:
            return full
        outputs = model.render_rays(ray_bundle.reshape((num_rays,))[rays], normals=normals)
        for key in keys:
            full[key][rays] = outputs[key].reshape(count, -1).to(full[key].dtype)
        return full
