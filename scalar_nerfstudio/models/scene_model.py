"""The model nerfstudio's trainer, viewer, ``ns-eval`` and ``ns-render`` see: global + blocks + fusion.

:class:`ScalarSceneModel` holds one :class:`ScalarModel` for the coarse global model and one per
block (the same class: a block differs only by its region, its images and where its decoder came
from). Training runs one of them at a time (the pipeline picks it by step); rendering renders the
global model and the blocks that have started training, and fuses them per pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.models.base_model import Model
from torch import Tensor, nn
from torch.nn import Parameter

from scalar_nerfstudio.blocks.capacity import BlockCapacity
from scalar_nerfstudio.blocks.split import Block, BlockSplit
from scalar_nerfstudio.blocks.visibility import aabb_in_frustum
from scalar_nerfstudio.fusion import (
    ParsedFusionMode,
    fuse_outputs,
    fuse_weighted,
    idw_weights,
    nearest_block,
    parse_fusion_mode,
    select_winner,
)
from scalar_nerfstudio.metrics import psnr
from scalar_nerfstudio.model_components.rendering import facing_normals, normals_from_unit_interval, normals_to_unit_interval, safe_normalise
from scalar_nerfstudio.models.scalar_model import NormalsOutput, ScalarModel, ScalarModelConfig, near_far_collider
from scalar_nerfstudio.blocks.palette import BLOCK_PALETTE, GLOBAL_COLOUR

DecoderMode = Literal["finetune", "frozen", "independent"]
#: A block's region radius never drops below this (normalised scene units; cameras span [-1, 1]).
MIN_REGION_RADIUS = 0.05


@dataclass
class ScalarSceneModelConfig(ScalarModelConfig):
    """Global model + one local model per block, fused per pixel (paper Sec. 3.4)."""

    _target: Type = field(default_factory=lambda: ScalarSceneModel)
    fusion: str = "global"
    """How block renders are fused: global (closest to the global model's colour, the paper's), idw
    (Block-NeRF's inverse distance weighting), nearest, global-only, or block:<k>."""
    idw_gamma: float = 1.0
    """Exponent of inverse distance weighting (``idw`` fusion)."""
    skip_invisible_blocks: bool = True
    """When rendering a camera, skip blocks whose scaled AABB lies outside its view frustum."""


def block_region(block: Block) -> Tuple[Tuple[float, float, float], float]:
    """Centre and radius of a block's local model frame: its scaled AABB's centre and largest half-extent.

    The global model maps the camera layout's largest half-extent to 1 (nerfstudio's pose
    normalisation); a block does the same with its own scaled AABB, so its hash grid resolves the
    block as finely as the global grid resolves the whole scene.
    """
    half_extent = max((hi - lo) / 2.0 for lo, hi in zip(block.aabb_min, block.aabb_max))
    return block.centre, max(half_extent, MIN_REGION_RADIUS)


@dataclass(frozen=True)
class ParamGroup:
    """An optimiser parameter group: which model it belongs to and which part of that model it is."""

    block: Optional[int]
    """None: the global model; k: block k's model."""
    part: str
    """``encoder``, ``decoder`` or ``appearance``."""

    @property
    def name(self) -> str:
        """The group's name (a key of the optimisers): ``decoder``, ``block3.decoder``, ..."""
        return self.part if self.block is None else f"block{self.block}.{self.part}"


class ScalarSceneModel(NormalsOutput, Model):
    """Global model, block models and their fusion.

    Rendering outside training adds a fused ``normals`` output (see
    :attr:`ScalarModelConfig.render_normals`): each pixel's normal comes from the model that gave its
    colour (the same winner, or the same IDW weights), so ``ns-export pointcloud`` writes one merged
    cloud of what the fused render shows.

    Keyword args (from the pipeline):
        split: the :class:`BlockSplit` of the training images (indices into them).
        block_ids: which blocks this model holds (all of them, or one in a ``scalar-nerf-block`` run).
        block_capacities: {k: BlockCapacity} table size and finest resolution of block k's model
            (default: the config's field settings).
        decoder_mode: ``finetune`` / ``frozen`` (start from the global decoder) or ``independent``.
    """

    config: ScalarSceneModelConfig

    def populate_modules(self) -> None:
        """Build the global model and the block models."""
        self.config.enable_collider = True
        self.config.collider_params = {"near_plane": self.config.near_plane, "far_plane": self.config.far_plane}
        super().populate_modules()
        self.collider = near_far_collider(self.config)
        self._init_normals_output(self.config.render_normals)
        self.split: BlockSplit = self.kwargs["split"]
        self.block_ids: Tuple[int, ...] = tuple(self.kwargs.get("block_ids", range(self.split.num_blocks)))
        self.decoder_mode: DecoderMode = self.kwargs.get("decoder_mode", "finetune")
        if self.decoder_mode not in ("finetune", "frozen", "independent"):
            raise ValueError(f"decoder_mode {self.decoder_mode!r}: expected finetune, frozen or independent")
        num_images: Dict[int, int] = {b.index: len(b.image_indices) for b in self.split.blocks}  # sizes appearance embeddings
        self.fusion_mode: ParsedFusionMode = parse_fusion_mode(self.config.fusion, self.split.num_blocks)
        self._view_blocks: Optional[List[int]] = None
        self.rendered_models: set = set()
        """Models (block indices, "global") rendered since the last camera started (for reports)."""
        self.global_model = ScalarModel(config=self.config, scene_box=self.scene_box, num_train_data=self.num_train_data)
        capacities: Dict[int, BlockCapacity] = self.kwargs.get("block_capacities") or {}
        blocks = {}
        for index in self.block_ids:
            centre, radius = block_region(self.split.blocks[index])
            blocks[str(index)] = ScalarModel(
                config=self._block_config(capacities.get(index)), scene_box=self.scene_box, num_train_data=num_images[index],
                region_centre=centre, region_radius=radius,
            )
            if self.decoder_mode == "frozen":
                blocks[str(index)].field.decoder.requires_grad_(False)
        self.blocks = nn.ModuleDict(blocks)
        # Which blocks have started training (their decoder was initialised); saved in checkpoints.
        self.register_buffer("blocks_started", torch.zeros(self.split.num_blocks, dtype=torch.bool))
        self.register_buffer(
            "block_centres", torch.tensor([b.centre for b in self.split.blocks], dtype=torch.float32), persistent=False
        )

    def _block_config(self, capacity: Optional[BlockCapacity]) -> ScalarModelConfig:
        """The model config of a block: the shared one, with the block's table size and resolution."""
        if capacity is None:
            return self.config
        field_config = replace(self.config.field, log2_hashmap_size=capacity.log2_hashmap_size, max_resolution=capacity.max_resolution)
        return replace(self.config, field=field_config)

    # -------------------------------------------------------------- checkpoint layout
    #: Where the pipeline keeps this model in its state dict (nerfstudio's ``Pipeline._model``).
    PIPELINE_KEY_PREFIX = "_model."

    @classmethod
    def global_state(cls, pipeline_state: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """The global model's own state dict, out of a pipeline checkpoint's ``pipeline`` state."""
        prefix = f"{cls.PIPELINE_KEY_PREFIX}global_model."
        return {k[len(prefix):]: v for k, v in pipeline_state.items() if k.startswith(prefix)}

    @classmethod
    def block_keys(cls, pipeline_state: Dict[str, Tensor], block: int) -> List[str]:
        """The keys of block ``block``'s model in a pipeline checkpoint's ``pipeline`` state."""
        prefix = f"{cls.PIPELINE_KEY_PREFIX}blocks.{block}."
        return [k for k in pipeline_state if k.startswith(prefix)]

    @classmethod
    def started_key(cls) -> str:
        """The key of the ``blocks_started`` flags in a pipeline checkpoint's ``pipeline`` state."""
        return f"{cls.PIPELINE_KEY_PREFIX}blocks_started"

    # ------------------------------------------------------------------------------ phases
    def phase_model(self, block: Optional[int]) -> ScalarModel:
        """The model trained in a phase: the global model (block None) or block ``block``'s."""
        if block is None:
            return self.global_model
        if str(block) not in self.blocks:
            raise KeyError(f"block {block} is not held by this model (it holds {list(self.block_ids)})")
        return self.blocks[str(block)]

    @torch.no_grad()
    def begin_block(self, block: int) -> None:
        """Start block ``block``'s phase once: copy the global decoder into it (finetune / frozen)."""
        if bool(self.blocks_started[block]):
            return
        if self.decoder_mode != "independent":
            self.blocks[str(block)].field.decoder.load_state_dict(self.global_model.field.decoder.state_dict())
        self.blocks_started[block] = True

    def started_block_ids(self) -> List[int]:
        """Blocks held here whose training has started (the ones rendering fuses)."""
        return [b for b in self.block_ids if bool(self.blocks_started[b])]

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        """``encoder`` / ``decoder`` / ``appearance`` of the global model, ``block{k}.*`` of each block."""
        return {group.name: params for group, params in self.param_groups_by_model()}

    def param_groups_by_model(self) -> List[Tuple[ParamGroup, List[Parameter]]]:
        """Every parameter group with the model it belongs to (:class:`ParamGroup`), in
        :meth:`get_param_groups` order."""
        groups = [(ParamGroup(None, part), params) for part, params in self.global_model.get_param_groups().items()]
        for index in self.block_ids:
            groups += [(ParamGroup(index, part), params) for part, params in self.blocks[str(index)].get_param_groups().items()]
        return groups

    # --------------------------------------------------------------------------- rendering
    def set_fusion(self, mode: str | ParsedFusionMode) -> None:
        """Switch the fusion mode used by rendering (checked against the number of blocks)."""
        self.fusion_mode = parse_fusion_mode(mode, self.split.num_blocks)

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box=None, skip_invisible_blocks: Optional[bool] = None) -> Dict[str, Tensor]:
        """Render one camera, fusing only the blocks whose AABB can be in its view (``skip_invisible_blocks``,
        default: the config's)."""
        skip = self.config.skip_invisible_blocks if skip_invisible_blocks is None else skip_invisible_blocks
        self._view_blocks = self.visible_blocks(camera) if skip else None
        self.rendered_models: set = set()
        try:
            return super().get_outputs_for_camera(camera, obb_box=obb_box)
        finally:
            self._view_blocks = None

    def visible_blocks(self, camera: Cameras) -> List[int]:
        """Blocks whose scaled AABB is (possibly) inside ``camera``'s view frustum."""
        camera = camera.reshape(()) if camera.shape != () else camera
        pose = camera.camera_to_worlds.detach().cpu().numpy()
        intrinsics = [float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)]
        return [
            b.index for b in self.split.blocks
            if aabb_in_frustum(pose, *intrinsics, b.aabb_min, b.aabb_max)
        ]

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """Fused ``rgb`` [R, 3], ``depth`` [R, 1], ``accumulation`` [R, 1], ``block_winner`` [R, 1],
        ``block_colour`` [R, 3]; ``normals`` [R, 3] in [0, 1] when :meth:`normals_wanted`.

        ``block_winner`` is the index of the block that gave the pixel (-1: the global model);
        ``block_colour`` shows it in the block's viewer colour.
        """
        normals = self.normals_wanted()
        mode = self.fusion_mode
        block_ids = self._blocks_for(mode)
        if mode.kind == "nearest" and len(block_ids) > 1:  # render only the blocks some ray is nearest to
            centres = self.block_centres[block_ids].to(ray_bundle.origins.device)
            nearest = nearest_block(ray_bundle.origins.reshape(-1, 3), centres).reshape(-1)
            block_ids = [block_ids[i] for i in sorted(set(nearest.tolist()))]
        # The global model is rendered only where the fusion needs it (idw / nearest / block do not).
        # Its normals only where it is the output (with blocks, "global" takes every pixel from a block).
        global_outputs = (
            self.global_model.render_rays(ray_bundle, normals=normals and not block_ids)
            if mode.kind in ("global", "global-only") or not block_ids else None
        )
        self.rendered_models.update([*block_ids, *(["global"] if global_outputs is not None else [])])
        if not block_ids:
            winner = torch.full_like(global_outputs["accumulation"], -1.0)
            return {**global_outputs, "block_winner": winner, "block_colour": self._winner_colours(winner)}
        block_outputs = [self.blocks[str(b)].render_rays(ray_bundle, normals=normals) for b in block_ids]
        if mode.kind == "block":
            mode = ParsedFusionMode(kind="block", block_index=0)
        fused = fuse_outputs(
            mode, block_outputs, global_outputs,
            camera_origin=ray_bundle.origins.reshape(-1, 3),
            block_centres=self.block_centres[block_ids].to(ray_bundle.origins.device),
            gamma=self.config.idw_gamma,
        )
        if normals:
            fused["normals"] = self._fuse_normals(
                mode, block_outputs, global_outputs, fused["block_winner"].reshape(-1), ray_bundle,
                self.block_centres[block_ids].to(ray_bundle.origins.device),
            )
        position_to_id = torch.tensor([-1, *block_ids], dtype=torch.float32, device=fused["rgb"].device)
        fused["block_winner"] = position_to_id[fused["block_winner"].reshape(-1) + 1][:, None]
        fused["block_colour"] = self._winner_colours(fused["block_winner"])
        return fused

    def _fuse_normals(
        self,
        mode: ParsedFusionMode,
        block_outputs: List[Dict[str, Tensor]],
        global_outputs: Optional[Dict[str, Tensor]],
        winner: Tensor,
        ray_bundle: RayBundle,
        block_centres: Tensor,
    ) -> Tensor:
        """[R, 3] fused normals in [0, 1], following the colour's fusion.

        Args:
            mode: the fusion mode the colours were fused with ("block" already renumbered to 0).
            block_outputs: K block renders with ``normals`` [R, 3] in [0, 1].
            global_outputs: the global render (its ``normals`` are the fallback if present).
            winner: [R] position of each ray's winning block in ``block_outputs`` (-1: none).
            ray_bundle: the rendered rays (origins for IDW, directions for the fallback).
            block_centres: [K, 3] centres of the rendered blocks.

        A ray no model gives a normal (winner -1 without global normals) faces its camera.
        """
        directions = ray_bundle.directions.reshape(-1, 3)
        facing = facing_normals(directions)
        fallback = global_outputs["normals"] if global_outputs is not None and "normals" in global_outputs else normals_to_unit_interval(facing)
        stacked = torch.stack([outputs["normals"] for outputs in block_outputs])  # [K, R, 3]
        if mode.kind != "idw":
            return select_winner(stacked, winner, fallback=fallback)
        weights = idw_weights(ray_bundle.origins.reshape(-1, 3), block_centres, self.config.idw_gamma)  # [K, R]
        mixed = fuse_weighted(normals_from_unit_interval(stacked), weights, fallback=normals_from_unit_interval(fallback))
        return normals_to_unit_interval(safe_normalise(mixed, normals_from_unit_interval(fallback)))

    def _winner_colours(self, winner: Tensor) -> Tensor:
        """[R, 1] block indices (-1: global) -> [R, 3] viewer colours."""
        palette = torch.tensor([GLOBAL_COLOUR, *BLOCK_PALETTE.tolist()], dtype=torch.float32, device=winner.device)
        index = winner.reshape(-1).long()
        return palette[torch.where(index < 0, 0, 1 + index % len(BLOCK_PALETTE))]

    def _blocks_for(self, mode: ParsedFusionMode) -> List[int]:
        """Blocks to render for ``mode`` (none for global-only or before any block has trained)."""
        if mode.kind == "global-only":
            return []
        started = self.started_block_ids()
        if self._view_blocks is not None and mode.kind != "block":
            started = [b for b in started if b in self._view_blocks]
        if mode.kind == "block":
            return [mode.block_index] if mode.block_index in started else []
        return started

    # ------------------------------------------------------------------------- loss, metrics
    def get_metrics_dict(self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """PSNR of the fused render."""
        return {"psnr": psnr(outputs["rgb"].detach(), self._target_rgb(batch, outputs["rgb"]))}

    def get_loss_dict(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor], metrics_dict: Optional[Dict[str, Tensor]] = None
    ) -> Dict[str, Tensor]:
        """Photometric MSE of the fused render (evaluation only; training uses the phase's model)."""
        return {"rgb_loss": torch.mean((outputs["rgb"] - self._target_rgb(batch, outputs["rgb"])) ** 2)}

    _target_rgb = staticmethod(ScalarModel._target_rgb)

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        """PSNR, SSIM (LPIPS when available) of the fused image; images incl. the block winner map."""
        metrics, images = self.global_model.get_image_metrics_and_images(outputs, batch)  # (normals too, if rendered)
        if "block_winner" in outputs:
            images["block_winner"] = outputs["block_winner"]
        return metrics, images

