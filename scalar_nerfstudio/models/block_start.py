"""A block's model: how it is built (its frame, its capacity) and how its training phase starts.

``block_init`` says where a block's model starts from:

* ``global``: the block lives in the global model's frame and starts as a copy of it (table,
  occupancy grid, the appearance embeddings of the block's images);
* ``fresh``: its own frame over its scaled AABB (:func:`block_region`), an empty table;
* ``fitted``: as fresh, with the table fitted to the global model's encoding first (:func:`fit_block`).

``decoder_mode`` says whether it copies the global decoder (``finetune`` / ``frozen``) or not
(``independent``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Literal, Optional, Sequence, Tuple, get_args

import torch
from nerfstudio.data.scene_box import SceneBox
from torch import Tensor

from scalar_nerfstudio.blocks.capacity import BlockCapacity
from scalar_nerfstudio.blocks.observation import observed_at
from scalar_nerfstudio.blocks.split import Block
from scalar_nerfstudio.models.block_fit import EncodingFit, fit_encoding, occupied_cell_sampler
from scalar_nerfstudio.models.scalar_model import ScalarModel, ScalarModelConfig

DecoderMode = Literal["finetune", "frozen", "independent"]
DECODER_MODES: Tuple[str, ...] = get_args(DecoderMode)
BlockInit = Literal["global", "fresh", "fitted"]
BLOCK_INITS: Tuple[str, ...] = get_args(BlockInit)
#: A block's region radius never drops below this (normalised scene units; cameras span [-1, 1]).
MIN_REGION_RADIUS = 0.05


def check_block_start(decoder_mode: str, block_init: str) -> None:
    """Raise a ValueError naming the problem if ``decoder_mode`` or ``block_init`` is unknown, or if
    the two do not go together."""
    if decoder_mode not in DECODER_MODES:
        raise ValueError(f"decoder_mode {decoder_mode!r}: expected finetune, frozen or independent")
    if block_init not in BLOCK_INITS:
        raise ValueError(f"block_init {block_init!r}: expected one of {', '.join(BLOCK_INITS)}")
    if block_init == "fitted" and decoder_mode == "independent":
        raise ValueError("block_init fitted fits a block's table to the global model through the global decoder, "
                         "which decoder_mode independent does not copy: use decoder_mode finetune or frozen, or block_init fresh")


def block_region(block: Block) -> Tuple[Tuple[float, float, float], float]:
    """Centre and radius of a block's local model frame: its scaled AABB's centre and largest half-extent.

    The global model maps the camera layout's largest half-extent to 1 (nerfstudio's pose
    normalisation); a block does the same with its own scaled AABB, so its hash grid resolves the
    block as finely as the global grid resolves the whole scene.
    """
    half_extent = max((hi - lo) / 2.0 for lo, hi in zip(block.aabb_min, block.aabb_max))
    return block.centre, max(half_extent, MIN_REGION_RADIUS)


def block_model_config(config: ScalarModelConfig, capacity: Optional[BlockCapacity]) -> ScalarModelConfig:
    """The model config of a block: the shared one, with the block's table size and resolution."""
    if capacity is None:
        return config
    field_config = replace(config.field, log2_hashmap_size=capacity.log2_hashmap_size, max_resolution=capacity.max_resolution)
    return replace(config, field=field_config)


def new_block_model(config: ScalarModelConfig, *, capacity: Optional[BlockCapacity], block: Block, block_init: BlockInit,
                    scene_box: SceneBox, num_images: int, scene_radius: Optional[float]) -> ScalarModel:
    """Block ``block``'s model, freshly initialised: in the global model's frame (``block_init``
    global) or in its own (:func:`block_region`), with ``num_images`` appearance embeddings, its rays
    ending at the sphere of ``scene_radius`` (None: unbounded)."""
    centre, radius = ((0.0, 0.0, 0.0), 1.0) if block_init == "global" else block_region(block)
    return ScalarModel(
        config=block_model_config(config, capacity), scene_box=scene_box,
        num_train_data=num_images, region_centre=centre, region_radius=radius, scene_radius=scene_radius,
    )


@torch.no_grad()
def start_block(model: ScalarModel, global_model: ScalarModel, *, image_indices: Sequence[int], decoder_mode: DecoderMode,
                block_init: BlockInit, seed_occupancy: bool) -> None:
    """Start a block's phase on its freshly initialised ``model``: copy the global decoder into it
    (finetune / frozen); with ``block_init`` global, also the global table, occupancy grid and the
    appearance embeddings of the block's images (``image_indices`` into the global model's); else,
    with ``seed_occupancy``, mark its occupancy grid from the global model's density. (``fitted``
    then fits its table: :func:`fit_block`.)"""
    if decoder_mode != "independent":
        model.field.decoder.load_state_dict(global_model.field.decoder.state_dict())
    if block_init == "global":
        model.field.encoder.load_state_dict(global_model.field.encoder.state_dict())
        copy_appearance(model, global_model, image_indices)
        model.occupancy.load_state_dict(global_model.occupancy.state_dict())
        model.occupancy.seeded.fill_(True)
    elif seed_occupancy:
        model.seed_occupancy_from(global_model)


@torch.no_grad()
def fit_block(model: ScalarModel, global_model: ScalarModel, *, image_indices: Sequence[int], observation: Optional[Tensor],
              centre: Tensor, radius: float, seed: int, steps: int, points_per_step: int) -> EncodingFit:
    """``block_init`` fitted: a block's table fitted to the global model's encoding
    (:func:`~scalar_nerfstudio.models.block_fit.fit_encoding`), and its images' appearance embeddings copied.

    The points are drawn in the global model's occupied cells that the block's cameras observe
    (``observation``: [1, G^3] bool of the block; None: the occupied cells within twice the block's
    ``radius`` of its ``centre`` [3]; every occupied cell when none of them qualifies, every cell when
    none is occupied). ``seed`` seeds the draw.
    """
    grid = global_model.occupancy
    cells = torch.nonzero(grid.occupied).squeeze(-1)
    if cells.numel() == 0:
        cells = torch.arange(grid.occupied.numel(), device=grid.occupied.device)
    centres = global_model.unit_cube_to_world(grid.cell_centres()[cells])  # [C, 3] world
    if observation is not None:
        near_block = observed_at(observation, centres)[0].to(cells.device)
    else:
        near_block = torch.linalg.vector_norm(centres - centre, dim=-1) <= 2.0 * radius
    if bool(near_block.any()):
        cells = cells[near_block]
    generator = torch.Generator(device=cells.device).manual_seed(seed)
    sampler = occupied_cell_sampler(cells, grid.resolution, to_world=global_model.unit_cube_to_world, generator=generator)
    copy_appearance(model, global_model, image_indices)
    return fit_encoding(
        model.field.encoder, student_unit=model.world_to_unit_cube,
        teacher=global_model.field.encoder, teacher_unit=global_model.world_to_unit_cube,
        sample_points=sampler, steps=steps, points_per_step=points_per_step,
    )


@torch.no_grad()
def copy_appearance(model: ScalarModel, global_model: ScalarModel, image_indices: Sequence[int]) -> None:
    """Give a block's ``model`` the global model's appearance embeddings of the block's images
    (``image_indices`` into the global model's, in the block's order)."""
    rows = torch.tensor(image_indices, dtype=torch.long, device=model.field.appearance.weight.device)
    model.field.appearance.weight.copy_(global_model.field.appearance.weight[rows])
